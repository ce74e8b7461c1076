"""The errors of evclock's pytest plugin: their class and their exact message.

Invalid options are :class:`PluginOptionError` (a ``ValueError``), checked on the option parsers
directly; a test set up in a way the plugin cannot run is :class:`PluginUsageError` (a
``RuntimeError``), checked from the outside with ``pytester`` where a test module can reach it.
"""

from __future__ import annotations

import asyncio
import re
import types
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import evclock
from evclock.testing._guard import _run_guarded
from evclock.testing._options import Options, _parse_rtf, _parse_seconds, marker_options
from evclock.testing._runner import _finish_asyncgen
from evclock.testing.plugin import PluginOptionError, PluginUsageError

pytest_plugins = ["pytester"]

INNER_INI = """
[pytest]
filterwarnings =
    error
    ignore:Module already imported so cannot be rewritten:pytest.PytestAssertRewriteWarning
"""
DEFAULTS = Options(wall=False, rtf=None, wall_timeout=60.0, sim_timeout=None)


def raises_exactly(error: type[BaseException], message: str) -> Any:
    return pytest.raises(error, match="^" + re.escape(message) + "$")


def test_the_plugins_errors_are_evclock_errors_named_by_their_public_module() -> None:
    assert issubclass(PluginOptionError, evclock.EvClockError)
    assert issubclass(PluginOptionError, ValueError)
    assert issubclass(PluginUsageError, evclock.EvClockError)
    assert issubclass(PluginUsageError, RuntimeError)
    assert PluginOptionError.__module__ == PluginUsageError.__module__ == "evclock.testing.plugin"


# --------------------------------------------------------------------------- options


@pytest.mark.parametrize(
    ("parse", "message"),
    [
        (
            lambda: _parse_seconds("soon", "--evclock-wall-timeout"),
            "--evclock-wall-timeout must be a number of seconds or 'none', got 'soon'",
        ),
        (
            lambda: _parse_seconds([1], "evclock(sim_timeout=...)"),
            "evclock(sim_timeout=...) must be a number of seconds or None, got list",
        ),
        (
            lambda: _parse_seconds(-3, "evclock(wall_timeout=...)"),
            "evclock(wall_timeout=...) must be a positive number of seconds (0 or None disables "
            "it), got -3",
        ),
        (
            lambda: _parse_rtf("fast", "--evclock-rtf"),
            "--evclock-rtf must be a positive real-time factor or 'none', got 'fast'",
        ),
        (
            lambda: _parse_rtf(-1, "--evclock-rtf"),
            "--evclock-rtf: rtf must be a positive finite real-time factor (1.0 = real time), "
            "got -1; use rtf=None to run as fast as possible",
        ),
    ],
    ids=["seconds-text", "seconds-type", "seconds-negative", "rtf-text", "rtf-value"],
)
def test_bad_option_values(parse: Callable[[], object], message: str) -> None:
    with raises_exactly(PluginOptionError, message):
        parse()


class _MarkedItem:
    """Just enough of a pytest item for ``marker_options``: its evclock markers."""

    def __init__(self, *marks: pytest.MarkDecorator) -> None:
        self._marks = [mark.mark for mark in marks]

    def iter_markers(self, name: str) -> Iterator[pytest.Mark]:
        return iter(mark for mark in self._marks if mark.name == name)


@pytest.mark.parametrize(
    ("marker", "message"),
    [
        (
            pytest.mark.evclock(5),
            "@pytest.mark.evclock takes keyword arguments only (rtf, wall_timeout, sim_timeout, "
            "start, stall_timeout), got positional (5,)",
        ),
        (
            pytest.mark.evclock(real_time=True),
            "@pytest.mark.evclock got an unexpected argument 'real_time'; it accepts rtf, "
            "wall_timeout, sim_timeout, start, stall_timeout",
        ),
        (
            pytest.mark.evclock(stall_timeout=-2),
            "evclock(stall_timeout=...): stall_timeout must be a positive number of wall seconds "
            "or None, got -2",
        ),
        (
            pytest.mark.evclock(start="noon"),
            "evclock(start=...) must be sim seconds or a sim Time, got str",
        ),
        (
            pytest.mark.evclock(start=-1),
            "evclock(start=...): start must not be negative, got -1",
        ),
    ],
    ids=["positional", "unknown", "stall_timeout", "start-type", "start-value"],
)
def test_bad_marker_arguments(marker: pytest.MarkDecorator, message: str) -> None:
    with raises_exactly(PluginOptionError, message):
        marker_options(_MarkedItem(marker), DEFAULTS)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- usage, directly


def _state(**fields: object) -> Any:
    defaults: dict[str, object] = {
        "expect_sim": True,
        "kind": "evclock",
        "pybullet_source": None,
        "source_adopted": False,
    }
    return types.SimpleNamespace(**{**defaults, **fields})


async def _nothing() -> None:
    pass


def test_a_test_that_needs_sim_time_on_a_plain_loop_is_refused() -> None:
    async def main() -> None:
        loop = type(asyncio.get_running_loop()).__name__
        with raises_exactly(
            PluginUsageError,
            f"evclock: this test uses evclock but runs on {loop}, not a SimEventLoop",
        ):
            await _run_guarded(_nothing(), _state())

    asyncio.run(main())


def test_a_pybullet_world_its_loop_does_not_step_is_refused() -> None:
    async def main() -> None:
        await _run_guarded(_nothing(), _state(pybullet_source=object()))

    with raises_exactly(
        PluginUsageError,
        "evclock: the PyBullet world of this test is not stepped by its loop: the loop was "
        "created before the evclock_pybullet fixture (a loop shared with other tests?); use a "
        "function-scoped loop for tests that use evclock_pybullet",
    ):
        evclock.run(main())


def test_an_async_generator_fixture_yields_once() -> None:
    async def world() -> Any:
        yield 1
        yield 2

    async def main() -> None:
        agen = world()
        assert await agen.__anext__() == 1
        await _finish_asyncgen(agen, "world")

    with raises_exactly(
        PluginUsageError,
        "async generator fixture 'world' yielded more than once; an async fixture yields "
        "exactly one value",
    ):
        evclock.run(main())


# --------------------------------------------------------------------------- usage, from a test


def run_inner(pytester: pytest.Pytester, source: str, *args: str) -> pytest.RunResult:
    pytester.makeini(INNER_INI)
    pytester.makepyfile(source)
    return pytester.runpytest(
        "-p", "no:cacheprovider", "-p", "no:hypothesispytest",
        "-o", "asyncio_default_fixture_loop_scope=function", *args,
    )  # fmt: skip


def test_evclock_loop_requested_by_a_test_that_is_not_an_evclock_test(
    pytester: pytest.Pytester,
) -> None:
    result = run_inner(
        pytester,
        """
        def test_x(request):
            request.getfixturevalue("evclock_loop")
        """,
    )
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        [
            "E *evclock.testing.plugin.PluginUsageError: evclock fixtures are function-scoped; "
            "evclock_loop was requested by <Function test_x>, which is not an evclock test: "
            "request it as an argument of the test function, or mark the test with "
            "@pytest.mark.evclock"
        ]
    )


UNMARKED_ASYNC_TEST = """
import pytest

async def test_unmarked():
    assert True

@pytest.mark.anyio
async def test_anyio_runs_it():
    assert True
"""
PYTEST_OWN_MESSAGE = "*async def functions are not natively supported.*"
EVCLOCK_HINT = (
    "*evclock: to run this test on simulation time, mark it @pytest.mark.evclock (or a whole "
    "module with pytestmark = pytest.mark.evclock), or request the evclock_clock or "
    "evclock_loop fixture; evclock has no ini option that runs every async test (an "
    "asyncio_mode = auto): each one opts in*"
)


@pytest.mark.parametrize(
    "plugins",
    [("-p", "no:asyncio"), ()],
    ids=["without pytest-asyncio", "pytest-asyncio strict"],
)
def test_an_async_test_no_plugin_runs_fails_with_how_to_run_it_on_evclock(
    pytester: pytest.Pytester, plugins: tuple[str, ...]
) -> None:
    if plugins:
        pytester.makeini(INNER_INI)
        pytester.makepyfile(UNMARKED_ASYNC_TEST)
        result = pytester.runpytest(
            "-p", "no:cacheprovider", "-p", "no:hypothesispytest", *plugins, "-rf"
        )  # fmt: skip
    else:
        result = run_inner(pytester, UNMARKED_ASYNC_TEST, "-rf")
    result.assert_outcomes(passed=1, failed=1)  # anyio ran its test
    result.stdout.fnmatch_lines([PYTEST_OWN_MESSAGE, EVCLOCK_HINT])


def test_other_plugins_keep_the_async_tests_they_run_and_without_evclock_no_hint(
    pytester: pytest.Pytester,
) -> None:
    auto = run_inner(pytester, UNMARKED_ASYNC_TEST, "-o", "asyncio_mode=auto")
    auto.assert_outcomes(passed=2)  # pytest-asyncio runs the unmarked one
    without = pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "-p", "no:hypothesispytest", "-p", "no:asyncio",
        "-p", "no:evclock", "-rf",
    )  # fmt: skip
    without.assert_outcomes(passed=1, failed=1)
    without.stdout.fnmatch_lines([PYTEST_OWN_MESSAGE])
    assert "evclock:" not in without.stdout.str()


def test_anyio_with_another_backend_than_asyncio(pytester: pytest.Pytester) -> None:
    result = run_inner(
        pytester,
        """
        import pytest

        @pytest.fixture
        def anyio_backend():
            return "trio"

        @pytest.mark.anyio
        @pytest.mark.evclock
        async def test_x(evclock_loop):
            pass
        """,
    )
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(
        [
            "E *evclock.testing.plugin.PluginUsageError: evclock needs anyio's asyncio backend "
            "with evclock's loop, got 'trio'; make the anyio_backend fixture return the "
            "evclock_anyio_backend fixture's value"
        ]
    )


@pytest.mark.parametrize(
    ("source", "message"),
    [
        (
            """
            def test_x(request):
                request.getfixturevalue("evclock_pybullet")
            """,
            "evclock_pybullet is a function-scoped fixture of an evclock test: request it as an "
            "argument of the test function, or mark the test with @pytest.mark.evclock",
        ),
        (
            """
            import pytest

            @pytest.mark.asyncio(loop_scope="module")
            async def test_x(evclock_pybullet):
                pass
            """,
            "evclock_pybullet needs a loop of its own, but this test shares a module-scoped "
            "loop; drop loop_scope from its asyncio marker",
        ),
        (
            """
            def test_x(evclock_loop, request):
                request.getfixturevalue("evclock_pybullet")
            """,
            "evclock_pybullet must be set up before the test's loop is created, but a fixture "
            "set up earlier already created it",
        ),
        (
            """
            import pytest

            @pytest.mark.evclock(start=5)
            def test_x(evclock_pybullet):
                pass
            """,
            "evclock(start=...) applies to virtual time only; a PyBullet world starts at 0",
        ),
    ],
    ids=["not-an-evclock-test", "shared-asyncio-loop", "loop-made-first", "start"],
)
def test_evclock_pybullet_misuse(pytester: pytest.Pytester, source: str, message: str) -> None:
    result = run_inner(pytester, source)
    outcomes = result.parseoutcomes()
    assert outcomes.get("failed", 0) + outcomes.get("errors", 0) == 1, result.stdout.str()
    result.stdout.fnmatch_lines([f"E *evclock.testing.plugin.PluginUsageError: {message}"])
