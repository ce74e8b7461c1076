"""evclock's pytest plugin, tested from the outside with ``pytester`` (as anyio tests its own).

Each test writes a small test module, runs pytest on it in-process and checks the outcomes and
the exact messages. The inner runs see the plugin exactly as users do: through the ``pytest11``
entry point of the installed package, next to pytest-asyncio's and anyio's plugins.
"""

from __future__ import annotations

import re

import pytest

pytest_plugins = ["pytester"]

NO_OTHER_PLUGINS = ("-p", "no:asyncio", "-p", "no:anyio")
#: Where the budget's cancellation on the loop is the subject: no pytest-timeout hard stop
#: (budget + 1 s) that a loaded machine could reach first.
NO_HARD_STOP = ("-p", "no:timeout")

# Inner runs turn warnings into errors too: the plugin must stay warning-free. (An in-process
# run cannot assertion-rewrite the installed plugin, which this session imported already: an
# artifact of running pytest inside pytest that users never see.)
INNER_INI = """
[pytest]
filterwarnings =
    error
    ignore:Module already imported so cannot be rewritten:pytest.PytestAssertRewriteWarning
"""


@pytest.fixture(autouse=True)
def _inner_ini(pytester: pytest.Pytester) -> None:
    pytester.makeini(INNER_INI)


def run(pytester: pytest.Pytester, *args: str, hypothesis: bool = False) -> pytest.RunResult:
    """Run pytest in-process on the files written by the test."""
    if "no:asyncio" not in args:
        args = ("-o", "asyncio_default_fixture_loop_scope=function", *args)
    if not hypothesis:  # its end-of-session report re-imports hypothesis in each inner run
        args = ("-p", "no:hypothesispytest", *args)
    return pytester.runpytest("-p", "no:cacheprovider", *args)


# --------------------------------------------------------------------------- registration


def test_marker_and_options_are_registered(pytester: pytest.Pytester) -> None:
    result = run(pytester, "--markers")
    result.stdout.fnmatch_lines(
        [
            "@pytest.mark.evclock(rtf=None, wall_timeout=60, sim_timeout=None, start=0, "
            "stall_timeout=60): run the test and its async fixtures on evclock's simulation "
            "loop (virtual time)*"
        ]
    )
    result = run(pytester, "--help")
    result.stdout.fnmatch_lines(
        [
            "evclock: simulation time for asyncio tests:",
            "  --evclock-wall * run evclock tests on wall time*",
            "  --evclock-rtf=FACTOR*",
            "  --evclock-wall-timeout=SECONDS*",
            "  --evclock-sim-timeout=SECONDS*",
        ]
    )


def test_a_project_using_the_plugin_sees_no_warning(pytester: pytest.Pytester) -> None:
    """A project with evclock[pytest] (pytest, pytest-timeout; no pytest-asyncio) and no
    configuration at all: no warning summary, in a separate process as a user runs it."""
    pytester.makeini("[pytest]\n")
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        @pytest.mark.evclock
        async def test_a_minute(evclock_clock):
            await asyncio.sleep(60)
            assert evclock_clock.now().seconds == 60
        """
    )
    result = pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "-p", "no:asyncio", "-p", "no:anyio", "-p", "no:hypothesispytest"
    )
    result.assert_outcomes(passed=1, warnings=0)
    assert "warnings summary" not in result.stdout.str()


#: A user project that has pytest-asyncio: plain pytest-asyncio tests, and evclock tests run by
#: evclock itself and by pytest-asyncio (with evclock's loop).
_WITH_PYTEST_ASYNCIO = {
    "test_plain": """
        import asyncio
        import pytest
        import pytest_asyncio

        @pytest_asyncio.fixture
        async def ready():
            await asyncio.sleep(0)
            return True

        @pytest.mark.asyncio
        async def test_plain(ready):
            assert ready
        """,
    "test_evclock": """
        import asyncio
        import pytest

        @pytest.mark.evclock
        async def test_on_evclocks_runner(evclock_clock):
            await asyncio.sleep(60)
            assert evclock_clock.now().seconds == 60

        @pytest.mark.asyncio
        @pytest.mark.evclock
        async def test_on_pytest_asyncio(evclock_clock):
            await asyncio.sleep(60)
            assert evclock_clock.now().seconds == 60
        """,
}
_QUIET = ("-p", "no:cacheprovider", "-p", "no:anyio", "-p", "no:hypothesispytest")
_UNSET_WARNING = 'The configuration option "asyncio_default_fixture_loop_scope" is unset.'


def warnings_shown(result: pytest.RunResult) -> str:
    """Every warning the run showed: its warnings summary (empty when there is none) and what
    it wrote to stderr (where a warning raised while pytest configures itself goes)."""
    lines = result.stdout.lines
    starts = [i for i, line in enumerate(lines) if "warnings summary" in line]
    summary: list[str] = []
    if starts:
        section = lines[starts[0] + 1 :]
        summary = section[: next(i for i, line in enumerate(section) if line.startswith("-- "))]
    return "\n".join([*summary, *result.stderr.lines]).strip()


def test_a_project_with_pytest_asyncio_and_its_ini_line_sees_no_warning(
    pytester: pytest.Pytester,
) -> None:
    pytester.makeini("[pytest]\nasyncio_default_fixture_loop_scope = function\n")
    pytester.makepyfile(**_WITH_PYTEST_ASYNCIO)
    result = pytester.runpytest_subprocess(*_QUIET)
    result.assert_outcomes(passed=3, warnings=0)
    assert warnings_shown(result) == ""


def test_without_the_ini_line_the_only_warning_is_pytest_asyncios_own(
    pytester: pytest.Pytester,
) -> None:
    """pytest-asyncio warns (on stderr, while pytest configures itself) until a project sets
    its option, with or without evclock: evclock adds no warning and causes none - the output
    is the same without evclock's plugin."""
    pytester.makeini("[pytest]\n")
    pytester.makepyfile(**_WITH_PYTEST_ASYNCIO)
    with_evclock = pytester.runpytest_subprocess(*_QUIET)
    with_evclock.assert_outcomes(passed=3)
    without_evclock = pytester.runpytest_subprocess(*_QUIET, "-p", "no:evclock", "test_plain.py")
    without_evclock.assert_outcomes(passed=1)
    shown = warnings_shown(with_evclock)
    assert shown == warnings_shown(without_evclock)
    first = re.escape(f": PytestDeprecationWarning: {_UNSET_WARNING}")
    assert re.fullmatch(rf".*pytest_asyncio[/\\]plugin\.py:\d+{first}", shown.splitlines()[0])
    assert "evclock" not in shown


@pytest.mark.parametrize(
    ("args", "header"),
    [
        ((), "evclock: sim time, rtf=none, wall-timeout=60 s, sim-timeout=none"),
        (
            ("--evclock-rtf=2", "--evclock-wall-timeout=5", "--evclock-sim-timeout=30"),
            "evclock: sim time, rtf=2, wall-timeout=5 s, sim-timeout=30 s",
        ),
        (
            ("--evclock-wall", "--evclock-wall-timeout=none"),
            "evclock: wall time (--evclock-wall), wall-timeout=none, sim-timeout=none",
        ),
    ],
)
def test_report_header(pytester: pytest.Pytester, args: tuple[str, ...], header: str) -> None:
    pytester.makepyfile("def test_nothing(): pass")
    result = run(pytester, *args)
    result.stdout.fnmatch_lines([header])
    result.assert_outcomes(passed=1)


def test_ini_keys_and_cli_precedence(pytester: pytest.Pytester) -> None:
    pytester.makeini(
        INNER_INI
        + """
evclock_rtf = 3
evclock_wall_timeout = 7
evclock_sim_timeout = 90
"""
    )
    pytester.makepyfile("def test_nothing(): pass")
    run(pytester).stdout.fnmatch_lines(
        ["evclock: sim time, rtf=3, wall-timeout=7 s, sim-timeout=90 s"]
    )
    run(pytester, "--evclock-rtf=none", "--evclock-sim-timeout=0").stdout.fnmatch_lines(
        ["evclock: sim time, rtf=none, wall-timeout=7 s, sim-timeout=none"]
    )


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (
            "--evclock-wall-timeout=soon",
            "ERROR: evclock: --evclock-wall-timeout must be a number of seconds or 'none', "
            "got 'soon'",
        ),
        (
            "--evclock-sim-timeout=-3",
            "ERROR: evclock: --evclock-sim-timeout must be a positive number of seconds "
            "(0 or None disables it), got -3.0",
        ),
        (
            "--evclock-rtf=fast",
            "ERROR: evclock: --evclock-rtf must be a positive real-time factor or 'none', "
            "got 'fast'",
        ),
        ("--evclock-rtf=-1", "ERROR: evclock: --evclock-rtf: rtf must be a positive finite*"),
    ],
)
def test_bad_option_values_are_usage_errors(
    pytester: pytest.Pytester, option: str, message: str
) -> None:
    pytester.makepyfile("def test_nothing(): pass")
    result = run(pytester, option)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines([message])


# --------------------------------------------------------------------------- evclock's runner


@pytest.mark.parametrize("plugins", [(), NO_OTHER_PLUGINS], ids=["all-plugins", "evclock-only"])
def test_marked_async_test_runs_on_virtual_time(
    pytester: pytest.Pytester, plugins: tuple[str, ...]
) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import evclock

        @pytest.mark.evclock
        async def test_an_hour(evclock_clock, evclock_loop):
            assert isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)
            assert asyncio.get_running_loop() is evclock_loop
            assert evclock.clock() is evclock_clock
            await asyncio.sleep(3600)
            assert evclock_clock.now() == evclock.Time(seconds=3600, clock_type=evclock.SIM)

        async def test_fixture_alone_opts_in(evclock_clock):
            await evclock_clock.sleep(2.5)
            assert evclock_clock.now().seconds == 2.5
        """
    )
    run(pytester, *plugins).assert_outcomes(passed=2)


def test_unmarked_async_tests_are_left_alone(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        async def test_not_opted_in():
            pass

        @pytest.mark.evclock
        async def test_opted_in():
            pass
        """
    )
    result = run(pytester, *NO_OTHER_PLUGINS)
    result.assert_outcomes(passed=1, failed=1)
    result.stdout.fnmatch_lines(
        ["*_ test_not_opted_in _*", "async def functions are not natively supported."]
    )


def test_async_fixtures_run_on_the_test_loop(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import contextvars
        import pytest
        import evclock

        user = contextvars.ContextVar("user")
        teardown_times = []

        @pytest.fixture
        async def slow_setup():
            await asyncio.sleep(10)
            return evclock.clock().now().seconds

        @pytest.fixture
        async def session_user(slow_setup):
            user.set("robot")
            yield slow_setup
            await asyncio.sleep(5)
            teardown_times.append(evclock.clock().now().seconds)

        @pytest.mark.evclock
        async def test_fixture_time(session_user, evclock_clock):
            assert session_user == 10
            assert evclock_clock.now().seconds == 10
            assert user.get() == "robot"
            await asyncio.sleep(1)

        def test_teardown_ran_on_the_loop():
            assert teardown_times == [16]
        """
    )
    run(pytester, *NO_OTHER_PLUGINS).assert_outcomes(passed=2)


def test_async_fixture_methods_are_bound_to_the_test_instance(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        class TestRobot:
            @pytest.fixture
            async def homed(self):
                await asyncio.sleep(3)
                self.homed_at = asyncio.get_running_loop().time()
                return self

            @pytest.mark.evclock
            async def test_homed(self, homed):
                assert homed is self
                assert self.homed_at == 3
        """
    )
    run(pytester).assert_outcomes(passed=1)


def test_higher_scoped_async_fixture_is_rejected(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.fixture(scope="module")
        async def world():
            return 1

        @pytest.mark.evclock
        async def test_world(world):
            pass
        """
    )
    result = run(pytester, *NO_OTHER_PLUGINS)
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(
        [
            "test_higher_scoped_async_fixture_is_rejected.py::test_world: async fixture 'world' "
            "is module-scoped, but evclock runs each test on its own loop; make it "
            "function-scoped, or let pytest-asyncio run these tests "
            "(@pytest.mark.asyncio(loop_scope=...)) on evclock's loop factory"
        ]
    )


def test_sync_test_can_drive_the_loop(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio

        def test_run_until_complete(evclock_loop, evclock_clock):
            evclock_loop.run_until_complete(asyncio.sleep(5))
            assert evclock_loop.time() == 5
            assert evclock_clock.now().seconds == 5
        """
    )
    run(pytester).assert_outcomes(passed=1)


def test_marker_options(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import evclock

        pytestmark = pytest.mark.evclock(start=5, rtf=8)

        def loop():
            return asyncio.get_running_loop()

        async def test_module_marker():
            assert loop().time() == 5
            assert loop().rtf == 8

        @pytest.mark.evclock(start=100)
        async def test_closest_marker_wins_per_argument():
            assert loop().time() == 100
            assert loop().rtf == 8

        @pytest.mark.evclock(rtf=None, start=evclock.Time(seconds=7, clock_type=evclock.SIM))
        async def test_none_and_time():
            assert loop().time() == 7
            assert loop().rtf is None
        """
    )
    run(pytester).assert_outcomes(passed=3)


def test_cli_rtf_is_the_default(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        @pytest.mark.evclock
        async def test_default():
            assert asyncio.get_running_loop().rtf == 2.5

        @pytest.mark.evclock(rtf=None)
        async def test_marker_overrides():
            assert asyncio.get_running_loop().rtf is None
        """
    )
    run(pytester, "--evclock-rtf=2.5").assert_outcomes(passed=2)


@pytest.mark.parametrize(
    ("marker", "message"),
    [
        (
            "evclock(real_time=True)",
            "*::test_x: @pytest.mark.evclock got an unexpected argument 'real_time'; it accepts "
            "rtf, wall_timeout, sim_timeout, start, stall_timeout",
        ),
        (
            "evclock(5)",
            "*::test_x: @pytest.mark.evclock takes keyword arguments only (rtf, wall_timeout, "
            "sim_timeout, start, stall_timeout), got positional (5,)",
        ),
        (
            "evclock(wall_timeout=-1)",
            "*::test_x: evclock(wall_timeout=...) must be a positive number of seconds "
            "(0 or None disables it), got -1",
        ),
        (
            "evclock(start='noon')",
            "*::test_x: evclock(start=...) must be sim seconds or a sim Time, got str",
        ),
        ("evclock(rtf=0)", "*::test_x: evclock(rtf=...): rtf must be a positive finite*"),
    ],
)
def test_marker_errors(pytester: pytest.Pytester, marker: str, message: str) -> None:
    pytester.makepyfile(
        f"""
        import pytest

        @pytest.mark.{marker}
        async def test_x():
            pass
        """
    )
    result = run(pytester)
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines([message])


def test_hypothesis_examples_run_on_the_loop(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        from hypothesis import given, settings, strategies as st
        import evclock

        examples = []

        @pytest.mark.evclock
        @settings(max_examples=5, database=None)
        @given(st.integers(min_value=1, max_value=1000))
        async def test_sleep(seconds):
            before = evclock.clock().now()
            await asyncio.sleep(seconds)
            assert (evclock.clock().now() - before).seconds == seconds
            examples.append(seconds)

        def test_all_examples_ran():
            assert len(examples) == 5
        """
    )
    run(pytester, *NO_OTHER_PLUGINS, hypothesis=True).assert_outcomes(passed=2)


# --------------------------------------------------------------------------- pytest-asyncio


def test_pytest_asyncio_runs_marked_tests_on_evclock_once(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import pytest_asyncio
        import evclock

        runs = []

        @pytest_asyncio.fixture
        async def warmed_up():
            await asyncio.sleep(10)
            return asyncio.get_running_loop()

        @pytest.mark.asyncio
        @pytest.mark.evclock(start=1)
        async def test_marked(warmed_up, evclock_clock):
            runs.append("marked")
            assert asyncio.get_running_loop() is warmed_up
            assert isinstance(warmed_up, evclock.SimEventLoop)
            assert evclock_clock.now().seconds == 11

        @pytest.mark.asyncio(loop_factories=["evclock"])
        async def test_selected_by_factory_name():
            runs.append("selected")
            assert isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)

        @pytest.mark.asyncio
        async def test_plain():
            runs.append("plain")
            assert not isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)

        def test_each_ran_once():
            assert sorted(runs) == ["marked", "plain", "selected"]
        """
    )
    result = run(pytester, "-v")
    result.assert_outcomes(passed=4)
    # One loop factory per test: pytest-asyncio hides the parameter, node ids are unchanged.
    result.stdout.fnmatch_lines(
        [
            "*::test_marked PASSED*",
            "*::test_selected_by_factory_name PASSED*",
            "*::test_plain PASSED*",
        ]
    )


def test_pytest_asyncio_auto_mode(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import evclock

        runs = []

        @pytest.fixture
        async def ready():
            await asyncio.sleep(2)

        @pytest.mark.evclock
        async def test_marked(ready):
            runs.append("marked")
            assert asyncio.get_running_loop().time() == 2

        async def test_plain():
            runs.append("plain")
            assert not isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)

        def test_each_ran_once():
            assert sorted(runs) == ["marked", "plain"]
        """
    )
    run(pytester, "--asyncio-mode=auto").assert_outcomes(passed=3)


def test_pytest_asyncio_module_loop_scope_shares_sim_time(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        pytestmark = [pytest.mark.asyncio(loop_scope="module"), pytest.mark.evclock]

        async def test_first():
            await asyncio.sleep(5)

        async def test_second(evclock_clock):
            assert evclock_clock.now().seconds == 5
        """
    )
    run(pytester).assert_outcomes(passed=2)


def test_pytest_asyncio_test_loop_from_a_sync_fixture(pytester: pytest.Pytester) -> None:
    """evclock_loop set up before pytest-asyncio makes its loop: evclock makes it then, and
    hands that same loop to pytest-asyncio (public hook only, no private runner fixture)."""
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import evclock

        @pytest.fixture
        def loop_seen_early(evclock_loop):
            return evclock_loop

        @pytest.mark.asyncio
        @pytest.mark.evclock(start=3)
        async def test_same_loop(loop_seen_early, evclock_loop, evclock_clock):
            assert asyncio.get_running_loop() is loop_seen_early is evclock_loop
            assert isinstance(evclock_loop, evclock.SimEventLoop)
            assert evclock_clock.now().seconds == 3

        @pytest.mark.asyncio(loop_factories=["asyncio", "evclock"])
        async def test_variants(request):
            import re
            from evclock.testing.plugin import PluginUsageError

            if isinstance(asyncio.get_running_loop(), evclock.SimEventLoop):
                request.getfixturevalue("evclock_loop")
            else:
                message = (
                    "::test_variants[asyncio]: this variant runs on another loop factory's "
                    "loop; evclock's fixtures need evclock's (select only 'evclock' in "
                    "loop_factories)"
                )
                with pytest.raises(PluginUsageError, match=re.escape(message) + "$"):
                    request.getfixturevalue("evclock_loop")
        """
    )
    pytester.makeconftest(
        """
        import asyncio

        def pytest_asyncio_loop_factories(config, item):
            return {"asyncio": asyncio.new_event_loop}
        """
    )
    run(pytester, "-v").assert_outcomes(passed=3)


def test_pytest_asyncio_selection_must_include_evclock(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncio(loop_factories=["asyncio"])
        @pytest.mark.evclock
        async def test_x():
            pass
        """
    )
    result = run(pytester)
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(
        [
            "*::test_x: the test uses evclock but @pytest.mark.asyncio(loop_factories="
            "[[]'asyncio'[]]) does not select 'evclock'; add it to the list"
        ]
    )


def test_other_loop_factory_hooks_keep_working(pytester: pytest.Pytester) -> None:
    pytester.makeconftest(
        """
        import asyncio

        class CustomLoop(asyncio.SelectorEventLoop):
            pass

        def pytest_asyncio_loop_factories(config, item):
            return {"custom": CustomLoop}
        """
    )
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import evclock

        @pytest.mark.asyncio
        async def test_custom():
            assert type(asyncio.get_running_loop()).__name__ == "CustomLoop"

        @pytest.mark.asyncio
        @pytest.mark.evclock
        async def test_evclock():
            assert isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)

        @pytest.mark.asyncio(loop_factories=["custom", "evclock"])
        async def test_both():
            pass
        """
    )
    result = run(pytester, "-v")
    result.assert_outcomes(passed=4)
    result.stdout.fnmatch_lines(
        ["*::test_both[[]custom[]] PASSED*", "*::test_both[[]evclock[]] PASSED*"]
    )


# --------------------------------------------------------------------------- anyio


def test_anyio_backend(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import anyio
        import pytest
        import evclock

        @pytest.fixture
        def anyio_backend(evclock_anyio_backend):
            return evclock_anyio_backend

        @pytest.fixture
        async def warmed_up():
            await anyio.sleep(10)
            return anyio.current_time()

        @pytest.mark.anyio
        @pytest.mark.evclock(start=5)
        async def test_anyio(warmed_up, evclock_clock):
            assert isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)
            assert warmed_up == 15
            with anyio.fail_after(100):
                await anyio.sleep(50)
            assert evclock_clock.now().seconds == 65

        @pytest.mark.anyio
        async def test_backend_alone_opts_in():
            await anyio.Event().wait()
        """
    )
    result = run(pytester)
    result.assert_outcomes(passed=1, failed=1)
    result.stdout.fnmatch_lines(
        [
            "E *evclock.DeadlockError: deadlock: *",
            "E *Task-* (the test): test_backend_alone_opts_in() at *",
        ]
    )


def test_anyio_with_a_plain_backend_is_an_error(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.fixture
        def anyio_backend():
            return "asyncio"

        @pytest.mark.anyio
        @pytest.mark.evclock
        async def test_x():
            pass
        """
    )
    result = run(pytester)
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(
        [
            "evclock: this test uses evclock but runs on _UnixSelectorEventLoop, not a "
            "SimEventLoop: anyio runs it with a plain asyncio backend. Make the anyio_backend "
            "fixture return evclock's backend:",
            "",
            "    @pytest.fixture",
            "    def anyio_backend(evclock_anyio_backend):",
            "        return evclock_anyio_backend",
        ]
    )


# --------------------------------------------------------------------------- failures

#: The same test under each runner: evclock's own, pytest-asyncio's, anyio's.
RUNNERS = {
    "evclock": "@pytest.mark.evclock",
    "pytest-asyncio": "@pytest.mark.asyncio\n@pytest.mark.evclock",
    "anyio": "@pytest.mark.anyio\n@pytest.mark.evclock",
}

HEADER = """\
import asyncio
import pytest

@pytest.fixture
def anyio_backend(evclock_anyio_backend):
    return evclock_anyio_backend
"""


def line_of(source: str, text: str) -> int:
    """The 1-based line number of the first line of ``source`` that ends with ``text``."""
    return next(n for n, line in enumerate(source.splitlines(), 1) if line.endswith(text))


@pytest.mark.parametrize("runner", list(RUNNERS))
def test_deadlock_fails_at_once_naming_the_tasks(pytester: pytest.Pytester, runner: str) -> None:
    source = f"""{HEADER}
async def helper(event):
    await event.wait()  # the helper waits here

{RUNNERS[runner]}
async def test_stuck():
    event = asyncio.Event()
    asyncio.get_running_loop().create_task(helper(event), name="helper")
    await asyncio.sleep(1)
    await event.wait()

{RUNNERS[runner]}
async def test_next_one_is_fine():
    await asyncio.sleep(1)
"""
    pytester.makepyfile(test_stuck=source)
    result = run(pytester)
    result.assert_outcomes(failed=1, passed=1)
    test_line = line_of(source, "    await event.wait()")
    helper_line = line_of(source, "# the helper waits here")
    result.stdout.fnmatch_lines(
        [
            "    async def test_stuck():",
            "*",
            ">       await event.wait()",
            "E       evclock.DeadlockError: deadlock: every task is waiting and nothing "
            "can wake one (no timer is scheduled, virtual time cannot advance on its own, no I/O "
            "or signal handler is registered, no child process runs and no other thread is "
            "working or waiting for I/O). Waiting tasks:",
            f"E         Task-* (the test): test_stuck() at *test_stuck.py:{test_line} -> "
            "Event.wait() at *locks.py:*, waiting on <Future pending*",
            f"E         helper: helper() at *test_stuck.py:{helper_line} -> Event.wait() at "
            "*locks.py:*, waiting on <Future pending*",
            "",
            f"test_stuck.py:{test_line}: DeadlockError",
        ]
    )


@pytest.mark.parametrize("runner", list(RUNNERS))
def test_wall_budget_cancels_a_test_that_keeps_the_loop_busy(
    pytester: pytest.Pytester, runner: str
) -> None:
    source = f"""{HEADER}
{RUNNERS[runner]}
async def test_busy():
    await asyncio.sleep(3)
    while True:
        await asyncio.sleep(0)

{RUNNERS[runner]}
async def test_next_one_is_fine():
    await asyncio.sleep(1)
"""
    pytester.makepyfile(test_busy=source)
    result = run(pytester, "--evclock-wall-timeout=0.2", *NO_HARD_STOP)
    result.assert_outcomes(failed=1, passed=1)
    result.stdout.fnmatch_lines(
        [
            ">           await asyncio.sleep(0)",
            "E *evclock.testing.plugin.WallTimeBudgetError: evclock: wall-time budget exceeded: "
            "the test was still running after 0.2 s of wall time (at sim time 3 s) and was "
            "cancelled. Its tasks were at:",
            f"E *Task-* (the test): test_busy() at *test_busy.py:"
            f"{line_of(source, 'await asyncio.sleep(0)')} -> sleep() at *",
            "E *Raise the budget with @pytest.mark.evclock(wall_timeout=...) or "
            "--evclock-wall-timeout (0 disables it).",
        ]
    )


def test_pytest_timeout_stops_a_test_blocking_its_loop(pytester: pytest.Pytester) -> None:
    source = """\
import asyncio
import pytest

@pytest.mark.evclock(wall_timeout=0.2)
async def test_stubborn():
    while True:
        pass

@pytest.mark.evclock
async def test_next_one_is_fine():
    await asyncio.sleep(1)
"""
    pytester.makepyfile(test_stubborn=source)
    result = run(pytester)
    result.assert_outcomes(failed=1, passed=1)
    # pytest-timeout's limit: the budget plus a grace period of at least 1 s.
    result.stdout.fnmatch_lines(
        [
            ">       while True:",  # stopped on the loop's back edge
            "E       Failed: Timeout (>1.2s) from pytest-timeout.",
            "*- evclock wall-time budget -*",
            "evclock: the wall-time budget (0.2 s) expired in call and the test was asked to "
            "stop between two callbacks of its loop; if it failed with pytest-timeout's "
            "'Timeout' instead, it did not get back to its loop in time: synchronous code "
            "blocked the loop, or the test swallowed CancelledError.",
        ]
    )


def test_a_test_that_swallows_the_cancellation_is_cancelled_again(
    pytester: pytest.Pytester,
) -> None:
    source = """\
import asyncio
import pytest

@pytest.mark.evclock(wall_timeout=0.2)
async def test_swallows_once():
    try:
        while True:
            await asyncio.sleep(0)
    except asyncio.CancelledError:
        pass
    while True:
        await asyncio.sleep(0)  # busy again
"""
    pytester.makepyfile(test_swallows=source)
    result = run(pytester, *NO_HARD_STOP)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        [
            ">           await asyncio.sleep(0)  # busy again",
            "E *evclock.testing.plugin.WallTimeBudgetError: evclock: wall-time budget exceeded: "
            "the test was still running after 0.2 s of wall time (at sim time 0 s) and was "
            "cancelled. Its tasks were at:",
        ]
    )


def test_pytest_timeouts_timer_thread_does_not_hide_a_paused_deadlock(
    pytester: pytest.Pytester,
) -> None:
    """pytest-timeout's thread method runs a timer thread during each test; it can never
    resume a paused loop, so the paused loop is still a deadlock (not a wait for that thread).
    A separate process: if it hung, its own 60 s limit would end it, not this session."""
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        @pytest.mark.evclock
        async def test_paused(evclock_loop):
            evclock_loop.pause()
            await asyncio.sleep(1)
        """
    )
    result = pytester.runpytest_subprocess(
        "-p",
        "no:cacheprovider",
        "-p",
        "no:asyncio",
        "--timeout=60",
        "-o",
        "timeout_method=thread",
        timeout=120,
    )
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        ["E *DeadlockError: the loop is paused and nothing could ever resume it*"]
    )


def test_without_pytest_timeout_a_blocked_test_fails_when_it_returns_to_its_loop(
    pytester: pytest.Pytester,
) -> None:
    source = """\
import time
import pytest

@pytest.mark.evclock(wall_timeout=0.2)
async def test_blocks_then_waits(evclock_clock):
    time.sleep(2)  # blocks the loop well past the budget
    await evclock_clock.sleep(1)
"""
    pytester.makepyfile(test_blocks=source)
    result = run(pytester, "-p", "no:timeout")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        [
            "evclock: pytest-timeout is not installed: a test blocked in synchronous code "
            "fails only once it returns to its loop (pip install 'evclock[pytest]')",
            "*",
            "E *evclock.testing.plugin.WallTimeBudgetError: evclock: wall-time budget exceeded: "
            "the test was still running after 0.2 s of wall time (at sim time 0 s) and was "
            "cancelled. Its tasks were at:",
        ]
    )


def test_pytest_timeout_limits_given_to_evclock_tests(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        def limit(request):
            marker = request.node.get_closest_marker("timeout")
            return None if marker is None else marker.args[0]

        @pytest.mark.evclock(wall_timeout=2)
        def test_budget_plus_grace(request):
            assert limit(request) == 4.0

        @pytest.mark.evclock(wall_timeout=100)
        def test_grace_is_at_most_ten_seconds(request):
            assert limit(request) == 110.0

        @pytest.mark.evclock(wall_timeout=300)
        def test_a_stricter_default_is_kept(request):
            assert limit(request) is None  # the --timeout=200 below applies

        @pytest.mark.timeout(7)
        @pytest.mark.evclock(wall_timeout=2)
        def test_own_marker_is_kept(request):
            assert limit(request) == 7

        @pytest.mark.evclock(wall_timeout=None)
        def test_no_budget_no_limit(request):
            assert limit(request) is None

        def test_not_an_evclock_test(request):
            assert limit(request) is None
        """
    )
    run(pytester, "--timeout=200").assert_outcomes(passed=6)


def test_wall_budget_covers_fixtures_and_sync_tests(pytester: pytest.Pytester) -> None:
    source = """\
import asyncio
import pytest

@pytest.fixture
async def busy_fixture():
    while True:
        await asyncio.sleep(0)  # spins

@pytest.mark.evclock(wall_timeout=0.2)
async def test_with_busy_fixture(busy_fixture):
    pass

async def spin():
    while True:
        await asyncio.sleep(0)

@pytest.mark.evclock(wall_timeout=0.2)
def test_sync_test_driving_the_loop(evclock_loop):
    evclock_loop.run_until_complete(spin())
"""
    pytester.makepyfile(test_slow_parts=source)
    result = run(pytester, *NO_OTHER_PLUGINS, *NO_HARD_STOP)
    result.assert_outcomes(failed=1, errors=1)
    result.stdout.fnmatch_lines(
        [
            "*_ ERROR at setup of test_with_busy_fixture _*",
            "E *evclock.testing.plugin.WallTimeBudgetError: evclock: wall-time budget exceeded: "
            "the test was still running after 0.2 s of wall time (in setup) and was cancelled. "
            "Its tasks were at:",
            f"E *Task-*: busy_fixture() at *test_slow_parts.py:{line_of(source, '# spins')} -> "
            "sleep() at *",
        ]
    )
    result.stdout.fnmatch_lines(
        [
            "*_ test_sync_test_driving_the_loop _*",
            "E *evclock.testing.plugin.WallTimeBudgetError: evclock: wall-time budget exceeded: "
            "the test was still running after 0.2 s of wall time and was cancelled. Its tasks "
            "were at:",
            "E *Task-*: spin() at *test_slow_parts.py:* -> sleep() at *",
        ]
    )


def test_sim_time_limit(pytester: pytest.Pytester) -> None:
    source = """\
import asyncio
import pytest

@pytest.fixture
async def warm_up():
    await asyncio.sleep(10)

@pytest.mark.evclock
async def test_forever(warm_up):
    while True:
        await asyncio.sleep(1)

@pytest.mark.evclock
async def test_limit_counts_from_the_test_start(warm_up):
    await asyncio.sleep(299)

@pytest.mark.evclock(sim_timeout=None)
async def test_marker_disables_it():
    await asyncio.sleep(10_000)
"""
    pytester.makepyfile(test_forever=source)
    result = run(pytester, "--evclock-sim-timeout=300")
    result.assert_outcomes(failed=1, passed=2)
    result.stdout.fnmatch_lines(
        [
            ">           await asyncio.sleep(1)",
            "E *evclock.SimTimeLimitError: evclock: sim-time limit exceeded: the test "
            "was still running after 300 s of sim time (at sim time 310 s) and was cancelled. "
            "Its tasks were at:",
            f"E *Task-* (the test): test_forever() at *test_forever.py:"
            f"{line_of(source, 'await asyncio.sleep(1)')} -> sleep() at *",
            "E *Raise the limit with @pytest.mark.evclock(sim_timeout=...) or "
            "--evclock-sim-timeout (0 disables it).",
        ]
    )


def test_sim_time_limit_does_not_hide_a_deadlock(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest

        @pytest.mark.evclock(sim_timeout=60)
        async def test_stuck():
            await asyncio.sleep(1)
            await asyncio.Event().wait()
        """
    )
    result = run(pytester)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["E *evclock.DeadlockError: deadlock: *"])


# --------------------------------------------------------------------------- wall mode


WALL_MODE_TESTS = """
import asyncio
import pytest
import evclock

@pytest.fixture
def anyio_backend(evclock_anyio_backend):
    return evclock_anyio_backend

async def check(clock):
    assert not isinstance(asyncio.get_running_loop(), evclock.SimEventLoop)
    assert isinstance(clock, evclock.WallClock)
    assert evclock.clock() is clock
    start = clock.now()
    await clock.sleep(0.01)
    assert (clock.now() - start).seconds >= 0.01

@pytest.mark.evclock
async def test_wall_time(evclock_clock):
    await check(evclock_clock)

@pytest.mark.asyncio
@pytest.mark.evclock
async def test_wall_time_pytest_asyncio(evclock_clock):
    await check(evclock_clock)

@pytest.mark.anyio
@pytest.mark.evclock
async def test_wall_time_anyio(evclock_clock):
    await check(evclock_clock)

def test_physics(evclock_pybullet):
    pass
"""


@pytest.mark.parametrize(
    ("args", "env"), [(("--evclock-wall",), None), ((), "0")], ids=["option", "environment"]
)
def test_wall_mode(
    pytester: pytest.Pytester,
    monkeypatch: pytest.MonkeyPatch,
    args: tuple[str, ...],
    env: str | None,
) -> None:
    if env is not None:
        monkeypatch.setenv("EVCLOCK_USE_SIM_TIME", env)
    pytester.makepyfile(WALL_MODE_TESTS)
    result = run(pytester, "-rs", *args)
    result.assert_outcomes(passed=3, skipped=1)
    result.stdout.fnmatch_lines(
        [
            f"evclock: wall time ({'EVCLOCK_USE_SIM_TIME' if env else '--evclock-wall'}), "
            "wall-timeout=60 s, sim-timeout=none",
            "*",
            "SKIPPED [[]1[]] *: evclock_pybullet needs sim time; --evclock-wall runs tests on "
            "wall time",
        ]
    )


# --------------------------------------------------------------------------- PyBullet

PYBULLET_TEST = """{header}
import pybullet as p
import evclock

{marks}
async def test_ball_drop(evclock_pybullet, evclock_clock):
    world = evclock_pybullet
    assert asyncio.get_running_loop().source is world.source
    p.loadURDF("plane.urdf", physicsClientId=world.client)
    ball = p.loadURDF("sphere2.urdf", [0, 0, 2], physicsClientId=world.client)
    await evclock_clock.sleep(1.0)
    assert world.source.step_index == 240
    assert evclock_clock.now().seconds == 1.0
    assert p.getBasePositionAndOrientation(ball, physicsClientId=world.client)[0][2] < 1.0
"""


@pytest.mark.pybullet
@pytest.mark.parametrize("runner", list(RUNNERS))
def test_pybullet_world_is_stepped_by_the_loop(pytester: pytest.Pytester, runner: str) -> None:
    pytester.makepyfile(PYBULLET_TEST.format(header=HEADER, marks=RUNNERS[runner]))
    run(pytester).assert_outcomes(passed=1)
