"""evclock's pytest plugin: run tests and their async fixtures on simulation time.

Installed with evclock (entry point ``pytest11``) and inactive until a test opts in, either with
the marker or by requesting one of the fixtures::

    @pytest.mark.evclock(sim_timeout=120)
    async def test_patrol(evclock_clock):
        await patrol(laps=3)                      # minutes of sim time, milliseconds of wall time
        assert evclock_clock.now().seconds == 90.0

Who runs an opted-in ``async def`` test:

* **pytest-asyncio** (>= 1.4), when it handles the test (``@pytest.mark.asyncio`` or auto mode):
  evclock answers its ``pytest_asyncio_loop_factories`` hook with an ``"evclock"`` loop factory;
  ``@pytest.mark.asyncio(loop_factories=["evclock"])`` selects it explicitly.
* **anyio**'s plugin, when the test uses ``anyio_backend``: make that fixture return the
  ``evclock_anyio_backend`` fixture's value.
* **evclock itself** otherwise: a fresh simulation loop per test, shared by the test's async
  fixtures (which must then be function-scoped).

An ``async def`` test that none of them runs fails with pytest's own message, to which evclock
adds how to opt in (there is no ``asyncio_mode = auto``-style option: each test opts in).

Each test is handled by exactly one of them, and ``@pytest.mark.evclock(...)`` is the single place
for per-test options whichever runs it: ``rtf``, ``start``, ``stall_timeout``, ``wall_timeout``
(a wall-clock budget for setup, call and teardown) and ``sim_timeout`` (a sim-time limit for the
test function). A deadlock fails at once with :class:`~evclock.DeadlockError` naming the waiting
tasks; an overrun fails with :class:`WallTimeBudgetError` or :class:`~evclock.SimTimeLimitError`.
The wall-time budget never raises into arbitrary code: it cancels the test on its loop, and a
test blocked in synchronous code is stopped by pytest-timeout, which evclock arms a grace period
after the budget (see :mod:`evclock.testing._budget`).

Command line and ini: ``--evclock-wall`` (run evclock tests on wall time: a plain asyncio loop on
which :func:`evclock.clock` is the wall clock), ``--evclock-rtf`` / ``evclock_rtf``,
``--evclock-wall-timeout`` / ``evclock_wall_timeout`` (default 60 s), ``--evclock-sim-timeout``
/ ``evclock_sim_timeout`` (default none).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import inspect
from collections.abc import Callable, Generator, Iterator, Mapping
from typing import Any, Final

import pytest

from evclock._errors import DeadlockError, PluginOptionError, PluginUsageError
from evclock._extras import import_extra
from evclock.hosts._current import attach_clock, attached_clock
from evclock.hosts._loop import SimEventLoop
from evclock.kernel._clock import Clock, WallClock
from evclock.sources import PyBulletTimeSource
from evclock.testing._budget import (
    Budget,
    PytestTimeoutHooks,
    WallTimeBudgetError,
    budget_errors,
    default_timeout_of,
    hard_limit,
)
from evclock.testing._describe import explain_deadlock
from evclock.testing._guard import guard, wrong_loop_message
from evclock.testing._options import DEFAULT_WALL_TIMEOUT, marker_options
from evclock.testing._runner import (
    RUNNER_FIXTURE,
    Runner,
    ensure_pybullet_first,
    wrap_async_fixture,
)
from evclock.testing._selection import (
    EVCLOCK_LOOP_FACTORY_NAME,
    asyncio_loop_scope,
    kind_of,
    locate_test_function,
    wants_evclock,
)
from evclock.testing._state import ITEM_STATE, SESSION, ItemState, Session, session_of, state_of

__all__ = [
    "EVCLOCK_LOOP_FACTORY_NAME",
    "PluginOptionError",
    "PluginUsageError",
    "PyBulletWorld",
    "WallTimeBudgetError",
    "evclock_anyio_backend",
    "evclock_clock",
    "evclock_loop",
    "evclock_pybullet",
]

_ANYIO_LOOP_FIXTURE: Final = "_evclock_anyio_loop"

# Errors show the name users import them by (evclock.testing.plugin.PluginUsageError).
PluginOptionError.__module__ = PluginUsageError.__module__ = __name__


# --------------------------------------------------------------------------- hooks


class _AsyncioHooks:
    """The pytest-asyncio integration, registered only when pytest-asyncio declares its hook."""

    def __init__(self, session: Session) -> None:
        self._session = session

    @pytest.hookimpl(wrapper=True)
    def pytest_asyncio_loop_factories(
        self, config: pytest.Config, item: pytest.Item
    ) -> Generator[None, Any, Mapping[str, Callable[[], asyncio.AbstractEventLoop]]]:
        result = yield
        return self._session.asyncio_factories(item, result)


#: How pytest's own message for an ``async def`` test no plugin ran begins (``async_fail``
#: in ``_pytest/python.py``, pytest 8 and 9).
_PYTEST_UNHANDLED_ASYNC = "async def functions are not natively supported"
_UNHANDLED_ASYNC_HINT = (
    "evclock: to run this test on simulation time, mark it @pytest.mark.evclock (or a whole "
    "module with pytestmark = pytest.mark.evclock), or request the evclock_clock or "
    "evclock_loop fixture; evclock has no ini option that runs every async test (an "
    "asyncio_mode = auto): each one opts in"
)


class _UnhandledAsyncHint:
    """Adds to pytest's failure of an ``async def`` test that no plugin ran (neither
    evclock, pytest-asyncio nor anyio) how to run it with evclock. A test another plugin
    runs, and any other failure, is left as it is."""

    @pytest.hookimpl(wrapper=True)
    def pytest_pyfunc_call(self, pyfuncitem: pytest.Function) -> Generator[None, object, object]:
        try:
            return (yield)
        except pytest.fail.Exception as exc:
            if state_of(pyfuncitem) is None and str(exc.msg).startswith(_PYTEST_UNHANDLED_ASYNC):
                raise pytest.fail.Exception(
                    f"{exc.msg}\n{_UNHANDLED_ASYNC_HINT}", pytrace=False
                ) from None
            raise


def pytest_addoption(parser: pytest.Parser) -> None:
    """Register evclock's command-line options and ini keys."""
    group = parser.getgroup("evclock", "evclock: simulation time for asyncio tests")
    group.addoption(
        "--evclock-wall",
        action="store_true",
        default=False,
        dest="evclock_wall",
        help="run evclock tests on wall time: a plain asyncio loop where evclock.clock() is "
        "the wall clock (also: EVCLOCK_USE_SIM_TIME=0)",
    )
    group.addoption(
        "--evclock-rtf",
        dest="evclock_rtf",
        default=None,
        metavar="FACTOR",
        help="default real-time factor of evclock tests: 'none' (as fast as possible, the "
        "default), 1 (real time), k (k x real time)",
    )
    group.addoption(
        "--evclock-wall-timeout",
        dest="evclock_wall_timeout",
        default=None,
        metavar="SECONDS",
        help=f"wall-time budget of each evclock test, setup to teardown (default "
        f"{DEFAULT_WALL_TIMEOUT}; 0 or 'none' disables it)",
    )
    group.addoption(
        "--evclock-sim-timeout",
        dest="evclock_sim_timeout",
        default=None,
        metavar="SECONDS",
        help="sim-time limit of each evclock test function (default none)",
    )
    parser.addini("evclock_rtf", "default for --evclock-rtf", default="none")
    parser.addini(
        "evclock_wall_timeout", "default for --evclock-wall-timeout", default=DEFAULT_WALL_TIMEOUT
    )
    parser.addini("evclock_sim_timeout", "default for --evclock-sim-timeout", default="none")


def pytest_configure(config: pytest.Config) -> None:
    """Register the marker, validate the options, hook into pytest-asyncio if present."""
    config.addinivalue_line(
        "markers",
        "evclock(rtf=None, wall_timeout=60, sim_timeout=None, start=0, stall_timeout=60): run "
        "the test and its async fixtures on evclock's simulation loop (virtual time)",
    )
    session = Session(config)
    config.stash[SESSION] = session
    config.pluginmanager.register(_UnhandledAsyncHint(), "evclock-async-hint")
    timeout_hook = getattr(config.hook, "pytest_timeout_set_timer", None)
    if timeout_hook is not None and timeout_hook.has_spec():
        config.pluginmanager.register(PytestTimeoutHooks(), "evclock-timeout")
    caller = getattr(config.hook, "pytest_asyncio_loop_factories", None)
    if caller is not None and caller.has_spec():
        config.pluginmanager.register(_AsyncioHooks(session), "evclock-asyncio")
        session.asyncio_hooked = True


def pytest_report_header(config: pytest.Config) -> list[str]:
    """The time base and the default budgets; who stops a test its loop cannot."""
    options = session_of(config).defaults

    def seconds(value: float | None) -> str:
        return "none" if value is None else f"{value:g} s"

    if options.wall:
        why = "--evclock-wall" if config.getoption("evclock_wall") else "EVCLOCK_USE_SIM_TIME"
        lines = [
            f"evclock: wall time ({why}), wall-timeout={seconds(options.wall_timeout)}, "
            f"sim-timeout={seconds(options.sim_timeout)}"
        ]
    else:
        rtf = "none" if options.rtf is None else f"{options.rtf:g}"
        lines = [
            f"evclock: sim time, rtf={rtf}, wall-timeout={seconds(options.wall_timeout)}, "
            f"sim-timeout={seconds(options.sim_timeout)}"
        ]
    if options.wall_timeout is not None and not config.pluginmanager.hasplugin("timeout"):
        lines.append(
            "evclock: pytest-timeout is not installed: a test blocked in synchronous code "
            "fails only once it returns to its loop (pip install 'evclock[pytest]')"
        )
    return lines


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, object, object]:
    """Track the running test (loop factories read its options), back its wall-time budget
    with pytest-timeout, and end the budget."""
    session = session_of(item.config)
    session.current_item = item
    _back_budget_with_pytest_timeout(item, session)
    try:
        return (yield)
    finally:
        state = state_of(item)
        if state is not None:
            if state.budget is not None:
                state.budget.finish()
            if state.early_loop is not None:  # made for pytest-asyncio, which never asked
                state.early_loop.close()
        session.current_item = None


def _back_budget_with_pytest_timeout(item: pytest.Item, session: Session) -> None:
    """Give an evclock test a pytest-timeout limit a little above its wall-time budget, so that
    a test its loop cannot stop (blocked in synchronous code) is stopped all the same - unless
    the test has its own timeout marker or pytest-timeout's default is stricter."""
    if not (
        isinstance(item, pytest.Function)
        and item.config.pluginmanager.hasplugin("timeout")
        and item.get_closest_marker("timeout") is None
        and wants_evclock(item)
    ):
        return
    try:
        wall_timeout = marker_options(item, session.defaults).wall_timeout
    except PluginOptionError:
        return  # setup reports it
    if wall_timeout is None:
        return
    limit = hard_limit(wall_timeout)
    default = default_timeout_of(item.config)
    if default is None or default > limit:
        item.add_marker(pytest.mark.timeout(limit))


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Resolve an opted-in test's options, pick its runner and start its wall-time budget."""
    if not isinstance(item, pytest.Function) or not wants_evclock(item):
        return
    session = session_of(item.config)
    try:
        options = marker_options(item, session.defaults)
    except PluginOptionError as exc:
        pytest.fail(f"{item.nodeid}: {exc}", pytrace=False)
    kind = kind_of(item)
    if kind == "asyncio" and not session.asyncio_hooked:
        pytest.fail(
            f"{item.nodeid}: pytest-asyncio runs this test but has no "
            "pytest_asyncio_loop_factories hook; upgrade it (pip install 'pytest-asyncio>=1.4'), "
            "or drop the asyncio marker to let evclock run the test",
            pytrace=False,
        )
    state = ItemState(item, options, kind)
    item.stash[ITEM_STATE] = state
    # evclock's runner, or a lease on anyio's: the loop then lives until teardown, so that a
    # failure can still be reported from the test's suspended frames.
    extra = (
        RUNNER_FIXTURE if kind == "evclock" else _ANYIO_LOOP_FIXTURE if kind == "anyio" else None
    )
    if extra is not None and state.is_async and extra not in item.fixturenames:
        item.fixturenames.append(extra)
    if options.wall_timeout is not None:
        state.budget = Budget(options.wall_timeout, state, session)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """Tell, next to a failure, that the wall-time budget had expired (when it is not the
    budget's own error that failed the test: pytest-timeout's, typically)."""
    report = yield
    state = state_of(item)
    budget = state.budget if state is not None else None
    if (
        budget is not None
        and report.failed
        and not (call.excinfo is not None and call.excinfo.errisinstance(WallTimeBudgetError))
    ):
        note = budget.blocked_note()
        if note is not None:
            report.sections.append(("evclock wall-time budget", note))
    return report


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item) -> Generator[None, object, object]:
    """End the wall-time budget once the test's fixtures are torn down."""
    state = state_of(item)
    try:
        if state is None:
            return (yield)
        if state.budget is not None:
            state.budget.enter_phase("teardown")
        with budget_errors(state):
            return (yield)
    finally:
        state = state_of(item)
        if state is not None and state.budget is not None:
            state.budget.finish()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, object, object]:
    """Put the budgets around the test function, whichever plugin runs it."""
    state = state_of(item)
    if state is None or not isinstance(item, pytest.Function):
        return (yield)
    if state.budget is not None:
        state.budget.enter_phase("call")
    if not state.is_async:
        with budget_errors(state):  # a sync test driving the loop itself
            return (yield)
    try:
        with _guarded_test_function(item, state):
            return (yield)
    except DeadlockError as exc:
        if state.call is None:
            raise
        raise explain_deadlock(exc, state.call) from None


@contextlib.contextmanager
def _guarded_test_function(item: pytest.Function, state: ItemState) -> Iterator[None]:
    """Make the plugin that runs an async test run it under evclock's guard.

    evclock's own runner applies the guard itself (``pytest_pyfunc_call``): nothing changes.
    pytest-asyncio and anyio call the test function they find on the item, and hypothesis
    the one it keeps as ``inner_test`` (the attribute it documents for this purpose): for the
    duration of the call, that attribute is the guarded function, then the original again.
    """
    holder, name = locate_test_function(item)
    if state.kind == "evclock" and holder is item:
        yield
        return
    original = getattr(holder, name)
    wrapped: Callable[..., Any] = guard(original, state)
    if state.kind == "evclock":  # hypothesis: run each example on our loop
        runner: Runner = item.funcargs[RUNNER_FIXTURE]  # type: ignore[assignment]
        guarded = wrapped

        @functools.wraps(original, updated=())
        def evclock_example(*args: Any, **kwargs: Any) -> None:
            runner.run(guarded(*args, **kwargs))

        wrapped = evclock_example
    setattr(holder, name, wrapped)
    try:
        yield
    finally:
        setattr(holder, name, original)


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """Run an opted-in ``async def`` test that no other plugin handles on evclock's runner."""
    state = state_of(pyfuncitem)
    if state is None or state.kind != "evclock" or not state.is_async:
        return None
    if not inspect.iscoroutinefunction(pyfuncitem.obj):
        return None  # hypothesis: pytest calls the (sync) test, which runs each example
    runner: Runner = pyfuncitem.funcargs[RUNNER_FIXTURE]  # type: ignore[assignment]
    funcargs = pyfuncitem.funcargs
    testargs = {arg: funcargs[arg] for arg in pyfuncitem._fixtureinfo.argnames}
    runner.run(guard(pyfuncitem.obj, state)(**testargs))
    return True


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_fixture_setup(
    fixturedef: pytest.FixtureDef[Any], request: pytest.FixtureRequest
) -> Generator[None, object, object]:
    """Run the async fixtures of a test evclock runs on that test's loop."""
    func = fixturedef.func
    if not (inspect.iscoroutinefunction(func) or inspect.isasyncgenfunction(func)):
        return (yield)
    item = session_of(request.config).current_item
    state = state_of(item) if item is not None else None
    if state is None:
        return (yield)
    if fixturedef.scope == "function":
        ensure_pybullet_first(request)
    if state.kind != "evclock":
        # pytest-asyncio or anyio run it, on the loop evclock gave them.
        with budget_errors(state):
            return (yield)
    if fixturedef.scope != "function":
        pytest.fail(
            f"{state.item.nodeid}: async fixture {fixturedef.argname!r} is {fixturedef.scope}-"
            "scoped, but evclock runs each test on its own loop; make it function-scoped, or "
            "let pytest-asyncio run these tests (@pytest.mark.asyncio(loop_scope=...)) on "
            "evclock's loop factory",
            pytrace=False,
        )
    fixturedef.func = wrap_async_fixture(func, request)  # type: ignore[misc]
    try:
        with budget_errors(state):
            return (yield)
    finally:
        fixturedef.func = func  # type: ignore[misc]


# --------------------------------------------------------------------------- fixtures


def _loop_of_test(request: pytest.FixtureRequest) -> asyncio.AbstractEventLoop:
    item = request.node
    state = state_of(item)
    if state is None or not isinstance(item, pytest.Function):
        raise PluginUsageError(
            f"evclock fixtures are function-scoped; {request.fixturename} was requested by "
            f"{item!r}, which is not an evclock test: request it as an argument of the test "
            "function, or mark the test with @pytest.mark.evclock"
        )
    ensure_pybullet_first(request)
    if state.kind == "asyncio":
        return session_of(request.config).asyncio_test_loop(state)
    if state.kind == "anyio":
        anyio_loop: asyncio.AbstractEventLoop = request.getfixturevalue(_ANYIO_LOOP_FIXTURE)
        return anyio_loop
    runner: Runner = request.getfixturevalue(RUNNER_FIXTURE)
    return runner.loop


@pytest.fixture
def evclock_loop(request: pytest.FixtureRequest) -> asyncio.AbstractEventLoop:
    """The event loop the test runs on: a :class:`~evclock.SimEventLoop` (a plain asyncio loop
    under ``--evclock-wall``). Use it for ``pause()``, ``step()``, ``rtf`` or, in a sync test,
    ``run_until_complete()``. Requesting it opts the test in, like the marker."""
    return _loop_of_test(request)


@pytest.fixture
def evclock_clock(evclock_loop: asyncio.AbstractEventLoop) -> Clock:
    """The clock the test runs on - what :func:`evclock.clock` returns inside it: the loop's
    :class:`~evclock.SimClock`, or the wall clock under ``--evclock-wall``."""
    if isinstance(evclock_loop, SimEventLoop):
        return evclock_loop.clock
    clock = attached_clock(evclock_loop)
    if clock is None:
        clock = WallClock()
        attach_clock(evclock_loop, clock)
    return clock


@pytest.fixture(scope="session")
def evclock_anyio_backend(request: pytest.FixtureRequest) -> tuple[str, dict[str, Any]]:
    """anyio's asyncio backend on evclock's loop (with the marker's options), for::

    @pytest.fixture
    def anyio_backend(evclock_anyio_backend):
        return evclock_anyio_backend
    """
    return ("asyncio", {"loop_factory": session_of(request.config).loop_factory})


@pytest.fixture(name=RUNNER_FIXTURE)
def _evclock_runner(request: pytest.FixtureRequest) -> Iterator[Runner]:
    """evclock's runner for a test no other plugin runs: the loop of the test and its async
    fixtures, created after its PyBullet world if it has one."""
    ensure_pybullet_first(request)
    runner = Runner(session_of(request.config).loop_factory)
    try:
        yield runner
    finally:
        runner.close()


@pytest.fixture(name=_ANYIO_LOOP_FIXTURE)
def _evclock_anyio_loop(request: pytest.FixtureRequest) -> Iterator[asyncio.AbstractEventLoop]:
    """Hold a lease on anyio's test runner (the one the test will run on) and give its loop."""
    from anyio.pytest_plugin import extract_backend_and_options, get_runner

    backend = request.getfixturevalue("anyio_backend")
    name, options = extract_backend_and_options(backend)
    if name != "asyncio":
        raise PluginUsageError(
            f"evclock needs anyio's asyncio backend with evclock's loop, got {backend!r}; make "
            "the anyio_backend fixture return the evclock_anyio_backend fixture's value"
        )
    with get_runner(name, options) as runner:
        loop: asyncio.AbstractEventLoop = runner.get_loop()  # type: ignore[attr-defined]
        state = state_of(request.node)
        if state is not None and state.expect_sim and not isinstance(loop, SimEventLoop):
            pytest.fail(wrong_loop_message(state, loop), pytrace=False)
        yield loop


@dataclasses.dataclass(frozen=True)
class PyBulletWorld:
    """A PyBullet physics client whose time is the test's sim time.

    ``client`` is the ``physicsClientId`` to pass to every ``pybullet`` call; ``source`` is the
    :class:`~evclock.sources.PyBulletTimeSource` that steps it (``source.set_time_step(...)``,
    ``source.add_step_hook(...)``, ``await source.wait_until(...)``). Gravity is -9.81 m/s^2
    along z, the time step PyBullet's default 1/240 s, and ``pybullet_data`` is on the search
    path: ``p.loadURDF("plane.urdf", physicsClientId=world.client)``.
    """

    client: int
    source: PyBulletTimeSource


@pytest.fixture
def evclock_pybullet(request: pytest.FixtureRequest) -> Iterator[PyBulletWorld]:
    """A PyBullet world (a DIRECT client) stepped by the test's loop: physics advances only when
    every task waits, in whole steps, in lockstep with the code under test.

    The world is created before the test's loop, which is then built around it; the client is
    disconnected after the loop closes. Requesting it opts the test in, like the marker.
    Skipped under ``--evclock-wall`` (a PyBullet world needs sim time).
    """
    state = state_of(request.node)
    if state is None:
        raise PluginUsageError(
            "evclock_pybullet is a function-scoped fixture of an evclock test: request it as an "
            "argument of the test function, or mark the test with @pytest.mark.evclock"
        )
    if state.options.wall:
        pytest.skip("evclock_pybullet needs sim time; --evclock-wall runs tests on wall time")
    loop_scope = asyncio_loop_scope(state.item)
    if state.kind == "asyncio" and loop_scope != "function":
        raise PluginUsageError(
            f"evclock_pybullet needs a loop of its own, but this test shares a {loop_scope}-"
            "scoped loop; drop loop_scope from its asyncio marker"
        )
    if state.loops:
        raise PluginUsageError(
            "evclock_pybullet must be set up before the test's loop is created, but a fixture "
            "set up earlier already created it"
        )
    if state.options.start_ns:
        raise PluginUsageError(
            "evclock(start=...) applies to virtual time only; a PyBullet world starts at 0"
        )
    pybullet = import_extra("pybullet", "pybullet", needed_by="the evclock_pybullet fixture")
    pybullet_data = import_extra("pybullet_data", "pybullet", needed_by="evclock_pybullet")
    source = PyBulletTimeSource.connect()
    try:
        client = source.client
        pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        state.pybullet_source = source
        yield PyBulletWorld(client, source)
    finally:
        source.close()  # disconnects the client (already done if the loop closed it)
