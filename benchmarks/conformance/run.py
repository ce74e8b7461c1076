"""Conformance: asyncio's and anyio's own test suites, on the default loop and on SimEventLoop.

A faithful asyncio loop passes CPython's ``test_asyncio`` and anyio's test suite except the
tests that measure wall time. This runner checks it: it runs every module of both suites in
its own subprocess (with a wall timeout), once on the default loop and once with every new
event loop being a ``SimEventLoop``, then prints pass/fail/skip per module for both and the
tests that pass on the default loop but not on ``SimEventLoop``. Those must all be in
``allowlist.toml`` (each with its reason); anything else makes the exit status 1.

So that CI never fails at random, a test that fails on the default loop is not counted, and
a test that passes on the default loop and fails on ``SimEventLoop`` (and is not
allow-listed) is run once more, alone, in a fresh process on ``SimEventLoop`` before it
counts; if it passes then, it counts as a pass and the report lists it among the tests that
passed only on the re-run (an intermittent gap worth a look, not a failure). The allow-list
has a section per suite (every Python) and may have one per suite and Python version
(``[asyncio."3.13"]``). The report ends with one line per suite:
``conformance SUITE on Python 3.X: OK|FAILED: ...``. CI (``.ci/run``) runs ``--suite
asyncio`` on every supported Python and both suites on 3.11.

* ``test_asyncio`` comes from the interpreter's own ``test`` package (Debian and some
  pyenv builds leave it out: then the runner says so and exits 2).
* anyio's suite comes from the sdist of the installed anyio version (the ``conformance``
  extra pins it: ``pip install -e '.[conformance]'``, which also installs what the suite
  needs), downloaded with pip into ``benchmarks/results/conformance/`` on first use. Only its
  plain asyncio backend runs.

Usage, from the repository root::

    .venv/bin/python benchmarks/conformance/run.py                 # both suites, both loops
    .venv/bin/python benchmarks/conformance/run.py --suite asyncio --loop sim -m test_locks
    .venv/bin/python benchmarks/conformance/run.py --json results.json

The default run uses two worker processes; both suites on both loops take 10-20 minutes on
a 2-core machine.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import importlib.metadata
import json
import os
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "results" / "conformance"
LOOPS = ("default", "sim")
#: Wall seconds one module may take before it is killed (its running test then fails).
DEFAULT_MODULE_TIMEOUT = 300.0
#: anyio tests that run no event loop of ours: not run. test_sourceless_install creates a
#: virtualenv and pip-installs anyio from its sources into it (build dependencies from the
#: package index), bounded by a 60 s timeout; it needed the runner's re-run once in CI.
ANYIO_DESELECT = ("--deselect", "tests/test_lazyimport.py::test_sourceless_install")
#: After SIGABRT (faulthandler prints every thread's stack), wait this long before SIGKILL.
_ABORT_GRACE = 5.0
#: Wall seconds for the re-run of one test alone (a passing test takes a few seconds).
_RERUN_TIMEOUT = 120.0
_OUTCOMES = ("pass", "fail", "skip")


@dataclasses.dataclass
class ModuleRun:
    """The outcome of one module of one suite on one loop."""

    suite: str
    module: str
    loop: str
    outcomes: dict[str, str]  # test id -> pass | fail | skip
    details: dict[str, str]  # test id -> why it failed or was skipped
    timed_out: bool
    wall: float
    stderr_tail: str
    #: Tests that failed here, then passed when re-run alone in a fresh process.
    passed_on_rerun: list[str] = dataclasses.field(default_factory=list)

    def count(self, outcome: str) -> int:
        return sum(1 for value in self.outcomes.values() if value == outcome)


# ------------------------------------------------------------------ the suites


def asyncio_modules() -> list[str]:
    try:
        import test.test_asyncio as package
    except ImportError:
        sys.exit(
            "this Python has no test.test_asyncio (its 'test' package is not installed; "
            "Debian ships it as python3.X-test-suite... or use a python.org/pyenv build)"
        )
    folder = Path(package.__file__).parent
    return sorted(p.stem for p in folder.glob("test_*.py"))


def anyio_source() -> Path:
    """The tests of the installed anyio version, from its sdist (downloaded once)."""
    try:
        version = importlib.metadata.version("anyio")
    except importlib.metadata.PackageNotFoundError:
        sys.exit("anyio is not installed: pip install -e '.[conformance]' (it pins the version)")
    target = RESULTS / f"anyio-{version}"
    if (target / "tests").is_dir():
        return target
    RESULTS.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-binary", ":all:",
             "--no-deps", f"anyio=={version}", "-d", tmp],
            check=True,
            timeout=300,
        )  # fmt: skip
        (sdist,) = Path(tmp).glob("anyio-*.tar.gz")
        with tarfile.open(sdist) as archive:
            archive.extractall(RESULTS, filter="data")
    return target


def anyio_modules(source: Path) -> list[str]:
    tests = source / "tests"
    return sorted(str(p.relative_to(source)) for p in tests.rglob("test_*.py"))


def command_for(suite: str, module: str, out: Path, anyio_src: Path | None) -> list[str]:
    if suite == "asyncio":
        return [
            sys.executable,
            "-X",
            "faulthandler",
            str(HERE / "_asyncio_child.py"),
            module,
            str(out),
        ]
    assert anyio_src is not None
    return [
        sys.executable, "-X", "faulthandler", "-m", "pytest", module, "-q", "-p", "no:evclock",
        "-p", "no:cacheprovider", "-p", "_anyio_plugin", "--rootdir", str(anyio_src),
        "-c", str(anyio_src / "pyproject.toml"), *ANYIO_DESELECT,
    ]  # fmt: skip


# ------------------------------------------------------------------ running


def run_module(
    suite: str, module: str, loop: str, timeout: float, anyio_src: Path | None
) -> ModuleRun:
    """Run one module; when its process dies or hangs under a test, that test fails and the
    module goes on in a fresh process without the tests already run."""
    outcomes: dict[str, str] = {}
    details: dict[str, str] = {}
    stderr_tail = ""
    timed_out = False
    started = time.monotonic()
    while True:
        remaining = timeout - (time.monotonic() - started)
        if remaining <= 0:
            timed_out = True
            break
        new, new_details, returncode, stderr, hung = _attempt(
            suite, module, loop, remaining, anyio_src, skip=sorted(outcomes)
        )
        stderr_tail = (stderr_tail + stderr)[-6000:]
        details.update(new_details)
        culprit = [test for test, outcome in new.items() if outcome == "running"]
        outcomes.update(new)
        for test in culprit:
            outcomes[test] = "fail"
            details[test] = (
                f"the module's process hung under this test and was killed after {remaining:.0f} s"
                if hung
                else f"the module's process died under this test (exit status {returncode})"
            )
        if hung:
            timed_out = True
            break
        if not culprit and returncode in (0, 1, 5):  # the run ended normally (5: no tests)
            break
        if not new:  # died before running any test: the module itself is broken
            outcomes[f"{module}::<module>"] = "fail"
            details[f"{module}::<module>"] = f"exit status {returncode}: {stderr[-2000:]}"
            break
        # Died between or under tests (a stray signal, a per-test timeout): go on.
    wall = time.monotonic() - started
    return ModuleRun(suite, module, loop, outcomes, details, timed_out, wall, stderr_tail)


def rerun_sim_only_failures(
    sim: ModuleRun, default: ModuleRun, anyio_src: Path | None, allowed: dict[str, str]
) -> None:
    """Re-run, each alone in a fresh process on SimEventLoop, the tests of ``sim`` that
    failed there but passed on the default loop; a pass replaces the failure and is noted
    in ``sim.passed_on_rerun``. Allow-listed tests are not re-run: they cannot fail the run
    (and the known gaps among them would take a timeout each)."""
    for test in sorted(sim.outcomes):
        if sim.outcomes[test] != "fail" or default.outcomes.get(test) != "pass":
            continue
        if test in allowed:
            continue
        if test.endswith("::<module>"):
            continue  # the module itself failed: nothing to re-run alone
        outcomes, details, _, _, _ = _attempt(
            sim.suite, sim.module, "sim", _RERUN_TIMEOUT, anyio_src, skip=[], only=[test]
        )
        if outcomes.get(test) == "pass":
            sim.outcomes[test] = "pass"
            sim.passed_on_rerun.append(test)
        elif test in details:
            sim.details[test] += "\n(re-run alone: " + first_line(details[test]) + ")"


def _attempt(
    suite: str,
    module: str,
    loop: str,
    timeout: float,
    anyio_src: Path | None,
    skip: list[str],
    only: list[str] | None = None,
) -> tuple[dict[str, str], dict[str, str], int, str, bool]:
    """One process over the module, minus ``skip`` (and only ``only``, if given):
    (outcomes, details, exit status, stderr, whether it hung and was killed)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "results.jsonl"
        skip_file = Path(tmp) / "skip.txt"
        skip_file.write_text("".join(f"{test}\n" for test in skip), encoding="utf-8")
        env = dict(os.environ)
        env["EVCLOCK_CONFORMANCE_LOOP"] = loop
        env["EVCLOCK_CONFORMANCE_OUT"] = str(out)
        env["EVCLOCK_CONFORMANCE_SKIP"] = str(skip_file)
        env.pop("EVCLOCK_CONFORMANCE_ONLY", None)
        if only is not None:
            only_file = Path(tmp) / "only.txt"
            only_file.write_text("".join(f"{test}\n" for test in only), encoding="utf-8")
            env["EVCLOCK_CONFORMANCE_ONLY"] = str(only_file)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), env.get("PYTHONPATH")]))
        cwd = anyio_src if suite == "anyio" else tmp
        proc = subprocess.Popen(
            command_for(suite, module, out, anyio_src),
            cwd=cwd,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        hung = False
        try:
            _, stderr = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            hung = True
            os.killpg(proc.pid, signal.SIGABRT)  # faulthandler dumps every thread's stack
            try:
                _, stderr = proc.communicate(timeout=_ABORT_GRACE)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                _, stderr = proc.communicate(timeout=_ABORT_GRACE)
        outcomes, details = read_results(out)
    return outcomes, details, proc.returncode, stderr.decode(errors="replace"), hung


def read_results(path: Path) -> tuple[dict[str, str], dict[str, str]]:
    """Per test, the worst outcome recorded (fail > skip > pass), or "running"."""
    outcomes: dict[str, str] = {}
    details: dict[str, str] = {}
    if not path.exists():
        return outcomes, details
    rank = {"running": 0, "pass": 1, "skip": 2, "fail": 3}
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a kill
        test = record["test"]
        if record.get("event") == "start":
            outcomes.setdefault(test, "running")
            continue
        outcome = record["outcome"]
        if outcomes.get(test, "running") == "running" or rank[outcome] > rank[outcomes[test]]:
            outcomes[test] = outcome
            details[test] = record.get("detail", "")
    return outcomes, details


# ------------------------------------------------------------------ reporting


def python_version() -> str:
    return f"{sys.version_info.major}.{sys.version_info.minor}"


def load_allowlist(version: str | None = None) -> dict[str, dict[str, str]]:
    """Per suite, test id -> reason: the entries of ``[suite]`` plus those of the section
    ``[suite."3.X"]`` for this Python's version (a test that fails on one Python only)."""
    version = version or python_version()
    with open(HERE / "allowlist.toml", "rb") as f:
        data = tomllib.load(f)
    allow: dict[str, dict[str, str]] = {}
    for suite in ("asyncio", "anyio"):
        section = data.get(suite, {})
        entries = {test: reason for test, reason in section.items() if isinstance(reason, str)}
        for key, value in section.items():
            if isinstance(value, dict):
                if not (key.count(".") == 1 and key.replace(".", "").isdigit()):
                    raise SystemExit(
                        f"allowlist.toml: [{suite}.{key!r}] is not a Python version section; "
                        f'name per-Python sections [{suite}."3.X"]'
                    )
                if key == version:
                    entries.update(value)
            elif not isinstance(value, str):
                raise SystemExit(f"allowlist.toml: [{suite}] {key!r} must map to its reason")
        allow[suite] = entries
    return allow


def module_of(suite: str, test: str) -> str:
    """The module a test id belongs to (as ``asyncio_modules``/``anyio_modules`` name it)."""
    return test.split(".")[0] if suite == "asyncio" else test.split("::")[0]


def first_line(detail: str) -> str:
    lines = [line for line in detail.strip().splitlines() if line.strip()]
    return lines[-1].strip()[:160] if lines else ""


def report(runs: list[ModuleRun], loops: list[str], wall: float) -> int:
    allow = load_allowlist()
    summaries: list[str] = []
    by_key = {(r.suite, r.module, r.loop): r for r in runs}
    suites = sorted({r.suite for r in runs})
    unexpected: list[tuple[str, str, str]] = []
    allowed_seen: list[tuple[str, str]] = []
    totals: dict[tuple[str, str], dict[str, int]] = {}
    for suite in suites:
        print(f"\n== {suite}: pass/fail/skip per module" + "".join(f"  [{lp}]" for lp in loops))
        modules = sorted({r.module for r in runs if r.suite == suite})
        for module in modules:
            cells = []
            for loop in loops:
                r = by_key.get((suite, module, loop))
                if r is None:
                    cells.append(" " * 22)
                    continue
                counts = [r.count(o) for o in _OUTCOMES]
                tot = totals.setdefault((suite, loop), dict.fromkeys(_OUTCOMES, 0))
                for o, c in zip(_OUTCOMES, counts, strict=True):
                    tot[o] += c
                flag = " TIMEOUT" if r.timed_out else ""
                cells.append(f"{counts[0]:5d} {counts[1]:4d} {counts[2]:4d} {r.wall:5.0f}s{flag}")
            print(f"  {module:44s}" + " | ".join(cells))
        for loop in loops:
            tot = totals.get((suite, loop), dict.fromkeys(_OUTCOMES, 0))
            print(f"  total [{loop}]: {tot['pass']} pass, {tot['fail']} fail, {tot['skip']} skip")
        if "default" not in loops or "sim" not in loops:
            continue
        print(f"\n== {suite}: tests that pass on the default loop but not on SimEventLoop")
        count = 0
        for module in modules:
            base, sim = by_key.get((suite, module, "default")), by_key.get((suite, module, "sim"))
            if base is None or sim is None:
                continue
            for test, outcome in sorted(base.outcomes.items()):
                if outcome != "pass":
                    continue
                got = sim.outcomes.get(test, "not run")
                if got == "pass":
                    continue
                count += 1
                reason = allow[suite].get(test)
                if reason is not None:
                    allowed_seen.append((suite, test))
                    print(f"  allowed  {test}  ({got}; {reason})")
                else:
                    detail = first_line(sim.details.get(test, "")) or got
                    unexpected.append((suite, test, detail))
                    print(f"  FAIL     {test}  ({got}: {detail})")
        print(f"  {count} test(s) pass only on the default loop")
        outside = sum(1 for s, _, _ in unexpected if s == suite)
        rerun = [
            test for r in runs if r.suite == suite and r.loop == "sim" for test in r.passed_on_rerun
        ]
        print(f"\n== {suite}: tests that failed on SimEventLoop and passed only on the re-run")
        for line in rerun:
            print(f"  rerun    {line}")
        print(f"  {len(rerun)} test(s) passed only on the re-run")
        base_tot = totals.get((suite, "default"), dict.fromkeys(_OUTCOMES, 0))
        summaries.append(
            f"conformance {suite} on Python {python_version()}: "
            f"{'OK' if not outside else 'FAILED'}: {count} sim-only failure(s), "
            f"{outside} outside the allow-list, of {base_tot['pass']} passing on the default "
            f"loop; {len(rerun)} passed only on the re-run"
        )
    if "default" in loops and "sim" in loops:
        ran = {(r.suite, r.module) for r in runs}
        stale = [
            (suite, test)
            for suite in suites
            for test in allow[suite]
            if (suite, test) not in allowed_seen and (suite, module_of(suite, test)) in ran
        ]
        if stale:
            print("\n== allow-listed tests that did not fail only on SimEventLoop this run:")
            for suite, test in stale:
                print(f"  {suite}: {test}")
        print(
            f"\nSimEventLoop conformance: {len(unexpected)} test(s) fail outside the "
            f"allow-list, {len(allowed_seen)} allow-listed"
        )
    if summaries:
        print()
    for line in summaries:
        print(f"{line} ({wall:.0f} s wall for the run)")
    return 1 if unexpected else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--suite", choices=("asyncio", "anyio", "all"), default="all")
    parser.add_argument("--loop", choices=("default", "sim", "both"), default="both")
    parser.add_argument("-m", "--module", action="append", help="only these modules (repeat)")
    parser.add_argument("--jobs", type=int, default=2, help="modules run at once (default 2)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_MODULE_TIMEOUT)
    parser.add_argument("--json", type=Path, help="write every outcome to this file")
    parser.add_argument("-v", "--verbose", action="store_true", help="print failures' details")
    parser.add_argument(
        "--reuse-default",
        type=Path,
        metavar="JSON",
        help="take the default loop's outcomes from an earlier --json file instead of running "
        "them again (they do not depend on evclock): for quick iterations with --loop sim",
    )
    args = parser.parse_args()

    loops = list(LOOPS) if args.loop == "both" else [args.loop]
    reused: list[ModuleRun] = []
    if args.reuse_default:
        reused = [
            ModuleRun(**r)
            for r in json.loads(args.reuse_default.read_text(encoding="utf-8"))
            if r["loop"] == "default"
        ]
        loops = ["sim"]
    suites = ["asyncio", "anyio"] if args.suite == "all" else [args.suite]
    anyio_src = anyio_source() if "anyio" in suites else None
    jobs: list[tuple[str, str, str]] = []
    for suite in suites:
        modules = asyncio_modules() if suite == "asyncio" else anyio_modules(anyio_src)  # type: ignore[arg-type]
        if args.module:
            modules = [m for m in modules if any(sel in m for sel in args.module)]
        jobs += [(suite, module, loop) for module in modules for loop in loops]
    started = time.monotonic()
    runs: list[ModuleRun] = []
    modules_run = {(suite, module) for suite, module, _ in jobs}
    runs += [r for r in reused if (r.suite, r.module) in modules_run]
    done_before = len(runs)
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = [
            pool.submit(run_module, suite, module, loop, args.timeout, anyio_src)
            for suite, module, loop in jobs
        ]
        for future in concurrent.futures.as_completed(futures):
            r = future.result()
            runs.append(r)
            print(
                f"[{len(runs) - done_before}/{len(jobs)}] {r.suite} {r.module} on {r.loop}: "
                f"{r.count('pass')} pass, {r.count('fail')} fail, {r.count('skip')} skip "
                f"in {r.wall:.0f} s" + (" (TIMEOUT)" if r.timed_out else ""),
                flush=True,
            )
            if args.verbose and (r.timed_out or r.count("fail")):
                for test, outcome in sorted(r.outcomes.items()):
                    if outcome == "fail":
                        print(f"    {test}: {r.details.get(test, '')}")
                if r.timed_out:
                    print(r.stderr_tail)
    if ("default" in loops and "sim" in loops) or reused:
        allow = load_allowlist()
        defaults = {(r.suite, r.module): r for r in runs if r.loop == "default"}
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
            reruns = [
                pool.submit(rerun_sim_only_failures, r, base, anyio_src, allow[r.suite])
                for r in runs
                if r.loop == "sim" and (base := defaults.get((r.suite, r.module))) is not None
            ]
            for rerun in reruns:
                rerun.result()
    if args.json:
        args.json.write_text(
            json.dumps([dataclasses.asdict(r) for r in runs], indent=1), encoding="utf-8"
        )
    wall = time.monotonic() - started
    status = report(runs, ["default", *loops] if reused else loops, wall)
    print(f"(wall time {wall:.0f} s, {args.jobs} jobs)")
    sys.exit(status)


if __name__ == "__main__":
    main()
