"""Sim time across processes against same-run floors: lockstep rounds/s, instructions, KUKA split.

Usage: python benchmarks/remote_lockstep.py [--rounds 5000] [--participants 1 4 16]
           [--repeat 3] [--kuka/--no-kuka] [--instructions/--no-instructions]
           [--pinned/--no-pinned] [--cpu N] [--calls/--no-calls]
           [--against OTHER_CHECKOUT] [--json out.json]

One command measures everything below and ends with the project's targets, each marked
``met`` or ``NOT MET`` (about 2 minutes on a loaded 2-core machine). A round is what the
lockstep protocol exchanges per participant: a 9-byte GRANT(t) out, a 17-byte
DONE(t, next deadline) back.

Floors (the same exchange with no evclock), measured in forked processes:

* **ping-pong**: a blocking round trip between two Python processes over a Unix
  socketpair: the floor of any lockstep round between processes.
* **eventfd ping-pong**: the same blocking round trip over a pair of eventfds (how a
  shared-memory ring wakes its peer) instead of a socket: what a faster same-host transport
  could save per round at most.
* **fan-out ping-pong** of width N (each width in ``--participants`` above 1): one blocking
  process sends a GRANT to each of N processes over N socketpairs, then receives each
  one's DONE: the floor of a lockstep round with N participants.
* **asyncio floor**: shaped like a lockstep round of this design: the server side answers
  in a stock asyncio loop's reader callback, the participant side wakes a stock asyncio
  task per round through a future its reader callback resolves, and the task sends (the
  participant's ``await clock.sleep``). What a round costs in asyncio alone, before evclock
  does any work: the ceiling of any design in which the participant is an asyncio task.
* **pinned** (``--pinned``, default on): the ping-pong and the asyncio floor with both
  processes on one CPU (``os.sched_setaffinity``; ``--cpu``, default the last allowed),
  where a round costs no cross-CPU wake-up.

evclock:

* **lockstep rounds/s** with N participant processes over a Unix socket: the simulation
  (virtual time) serves; each participant sleeps 1 ms of sim time ``--rounds`` times, so
  every round grants all N and waits for all N DONEs. Reported as rounds per wall second,
  as a ratio of the floor of the same width (the ping-pong for 1, the fan-out ping-pong
  for N), and with the CPU time per round of the server and of each active participant
  (``time.process_time`` over the measured rounds: what a round costs, much less sensitive
  to the machine's load than wall time). With ``--pinned``, also 1 participant with both
  processes on the pinned CPU, against the pinned ping-pong.
* **idle participants cost nothing**: 1 active participant plus 15 that sleep an hour of sim
  time (no deadline due in any measured round); compare with the 1-participant figure.
* **instructions per round** (``--instructions``, default on; needs valgrind and gcc): the
  lockstep server and its one participant, each under ``valgrind --tool=callgrind
  --instr-atstart=no --collect-atstart=no``, count only around their measured rounds
  (callgrind's client requests, ``build_marks``/``_Marks`` of ``instructions.py``, loaded
  when BENCH_MARKS names the library): 100 rounds uncounted, then 300 and 600 counted
  (one dump each); (600 rounds' count - 300 rounds') / 300 is the steady-state cost per
  round, start-up and teardown cancelling out. Server, participant and their sum, beside
  the same for both sides of the ping-pong and of the asyncio floor (each side a process
  of its own under callgrind on one end of a socketpair; ``PYTHONHASHSEED=0`` for all).
  Exact and independent of the machine's load.
* **KUKA split**: KUKA reaching with physics at 240 Hz and its joint controller at 100 Hz
  and at 240 Hz (``control_hz``: a constructor argument of ``evclock_sims.kuka.KukaReach``,
  not a ``--param``, and ``--serve`` takes no ``--param``; so the script writes a one-class
  scenario file per rate and runs ``evclock run FILE:KukaControl``). ``evclock run ...
  --serve ... --remote-controllers`` with ``evclock control`` in another process, against
  the in-process ``evclock run``: physics steps per wall second of each (from their
  reports' ``wall_time_s``: the split one from the controllers' joining to their leaving)
  and the ratio; and whether the split run's trajectory is bit-identical to the in-process
  one (the reports' final state, sim time and summary of both split processes, and the
  loops' tick counts, as ``tests/remote/test_remote_split.py`` compares them), in every
  repetition.
* **Python calls per round** (``--calls``, default on): the same rounds under cProfile,
  counting the function calls of the server and of an active participant per round. Exact
  and independent of the machine's load: what a change removed, call by call.

Targets: lockstep rounds/s >= 0.5x the floor of the same width (1 participant: unpinned
and pinned; 4 and 16: the fan-out ping-pong); instructions per round, server + 1
participant, <= 25,000; KUKA split >= 0.7x the in-process steps/s at 100 Hz and 240 Hz
control, its trajectory bit-identical.

``--against DIR`` measures another checkout of evclock (``git worktree add /tmp/base main``)
in the same run, interleaved with this one (lockstep, KUKA, instructions and calls; the
floors are common): before/after figures of a change, each checkout with its targets.

Each wall figure is the best of ``--repeat`` runs, variants interleaved so that load from
elsewhere hits all alike (the KUKA ratio: best split rate over best in-process rate). Wall
time is what a round costs here, so a loaded machine lowers every figure; the ratios to
the same-run floors are the comparable numbers. ``--json`` writes every figure, and the
targets with their values and verdicts.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import instructions
from instructions import _Marks, build_marks

ROOT = Path(__file__).resolve().parent.parent
HERE = Path(__file__).resolve().parent
CLI = [sys.executable, "-c", "from evclock.tools._cli import main; main()"]

#: A lockstep round's frames: GRANT(t) out to a participant, DONE(t, next deadline) back.
GRANT, DONE = b"g" * 9, b"d" * 17
#: Under callgrind every measured process runs WARM uncounted rounds, then SMALL and BIG
#: counted ones (one dump each): (BIG - SMALL) rounds of difference per process.
WARM, SMALL, BIG = 100, 300, 600
SEGMENTS = f"{WARM},{SMALL},{BIG}"
#: The project's targets (same-run ratios, instructions per round).
ROUNDS_TARGET = 0.5
INSTRUCTIONS_TARGET = 25_000
KUKA_TARGET = 0.7
KUKA_CONTROL_HZ = (100.0, 240.0)

# The lockstep programs. With BENCH_CALLS, each counts its Python calls under cProfile. With
# BENCH_MARKS (the library of callgrind's client requests) and BENCH_SEGMENTS
# ("warm,small,big"), each counts instructions around its measured rounds only: WARM rounds
# first, then each counted segment between the marks (one dump each).
HEADER = textwrap.dedent(
    """
    import cProfile, json, os, pstats, sys, time, evclock
    profile = cProfile.Profile() if os.environ.get("BENCH_CALLS") else None
    marks = None
    if os.environ.get("BENCH_MARKS"):
        sys.path.append(os.environ["BENCH_DIR"])
        from instructions import _Marks
        marks = _Marks(os.environ["BENCH_MARKS"])
        warm, *counted = (int(n) for n in os.environ["BENCH_SEGMENTS"].split(","))
    """
)
SERVER = HEADER + textwrap.dedent(
    """
    async def main():
        count, rounds = int(sys.argv[2]), int(sys.argv[3])
        clock = evclock.clock()
        async with evclock.remote.serve(sys.argv[1]) as server:
            await server.wait_for_participants(count=count)
            if marks:
                marks.start_instrumentation()
                await clock.sleep(warm / 1000)
                for n in counted:  # n rounds of 1 ms
                    marks.begin()
                    await clock.sleep(n / 1000)
                    marks.end()
                await clock.sleep(0.01)  # the participants end their last segment
                return
            wall0, cpu0 = time.perf_counter(), time.process_time()
            if profile:
                profile.enable()
            await clock.sleep(rounds / 1000)  # `rounds` rounds of 1 ms
            if profile:
                profile.disable()
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        calls = pstats.Stats(profile).total_calls if profile else 0
        print(json.dumps({"rounds": rounds, "wall_s": wall, "cpu_s": cpu, "calls": calls}))
    evclock.run(main())
    """
)
# Active participants sleep 1 ms at a time (past the measured rounds: the server stops first
# and they end with ClockLostError, as expected); idle ones sleep an hour: no deadline is due.
# Active ones print the CPU seconds they spent from their first round to the end.
PARTICIPANT = HEADER + textwrap.dedent(
    """
    cpu0 = None
    async def main():
        global cpu0
        clock = evclock.clock()
        if sys.argv[1] == "idle":
            await clock.sleep(3600)
        if marks:
            marks.start_instrumentation()
            for _ in range(warm):
                await clock.sleep(0.001)
            for n in counted:
                marks.begin()
                for _ in range(n):
                    await clock.sleep(0.001)
                marks.end()
        await clock.sleep(0.001)
        cpu0 = time.process_time()
        if profile:
            profile.enable()
        while True:
            await clock.sleep(0.001)
    try:
        evclock.run(main())
    except evclock.ClockLostError:
        pass
    if cpu0 is not None:
        if profile:
            profile.disable()
        calls = pstats.Stats(profile).total_calls if profile else 0
        print(json.dumps({"cpu_s": time.process_time() - cpu0, "calls": calls}))
    """
)

# ------------------------------------------------------------------------------ the floors
# Each floor has a server side (given the sockets to its participants) and a participant
# side (given its socket), run for a number of rounds: in forked processes for wall time,
# and each in its own process under callgrind for instructions (``--side``).


def ping_pong_server(socks: list[socket.socket], rounds: int) -> None:
    """The blocking ping-pong's server: a GRANT out, the DONE back, per round."""
    (sock,) = socks
    for _ in range(rounds):
        sock.send(GRANT)
        sock.recv(64)


def ping_pong_participant(sock: socket.socket, rounds: int) -> None:
    """The blocking ping-pong's participant: a GRANT in, the DONE out, per round."""
    for _ in range(rounds):
        sock.recv(64)
        sock.send(DONE)


def fan_out_server(socks: list[socket.socket], rounds: int) -> None:
    """The fan-out ping-pong's server: a GRANT to each participant, then each one's DONE.
    (Its participants are :func:`ping_pong_participant`.)"""
    for _ in range(rounds):
        for sock in socks:
            sock.send(GRANT)
        for sock in socks:
            sock.recv(64)


def asyncio_server(socks: list[socket.socket], rounds: int) -> None:
    """The asyncio floor's server: a stock asyncio reader callback answers each DONE with
    the next GRANT."""
    (sock,) = socks
    loop = asyncio.new_event_loop()
    finished = loop.create_future()
    seen = 0

    def on_readable() -> None:
        nonlocal seen
        sock.recv(64)
        seen += 1
        sock.send(GRANT)
        if seen == rounds:
            loop.remove_reader(sock)
            finished.set_result(None)

    loop.add_reader(sock, on_readable)
    loop.run_until_complete(finished)
    loop.close()


def asyncio_participant(sock: socket.socket, rounds: int) -> None:
    """The asyncio floor's participant: a stock asyncio task sends DONE and awaits a future
    that its reader callback resolves with the next GRANT (``await clock.sleep``)."""
    loop = asyncio.new_event_loop()
    waiter: list[asyncio.Future[None]] = []

    def on_readable() -> None:
        sock.recv(64)
        if waiter and not waiter[0].done():
            waiter[0].set_result(None)

    async def main() -> None:
        loop.add_reader(sock, on_readable)
        for _ in range(rounds):  # tell DONE, wait for the next grant
            waiter[:] = [loop.create_future()]
            sock.send(DONE)
            await waiter[0]
        loop.remove_reader(sock)

    loop.run_until_complete(main())
    loop.close()


@dataclass(frozen=True)
class Floor:
    """A floor's two sides, and whether its sockets block."""

    server: Callable[[list[socket.socket], int], None]
    participant: Callable[[socket.socket, int], None]
    blocking: bool


FLOORS = {
    "ping-pong": Floor(ping_pong_server, ping_pong_participant, blocking=True),
    "fan-out": Floor(fan_out_server, ping_pong_participant, blocking=True),
    "asyncio": Floor(asyncio_server, asyncio_participant, blocking=False),
}


@contextlib.contextmanager
def pinned(cpu: int | None) -> Iterator[None]:
    """Run this process (and what it forks meanwhile) on ``cpu`` alone (None: unpinned)."""
    if cpu is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def floor_rate(
    name: str, width: int, rounds: int, cpu: int | None = None
) -> tuple[float, float, float]:
    """Rounds per wall second of floor ``name`` with ``width`` forked participants (pinned
    with this process to ``cpu`` if given), and the CPU microseconds per round of the
    server and of a participant (mean)."""
    floor = FLOORS[name]
    with pinned(cpu):
        pairs = [socket.socketpair() for _ in range(width)]
        report_r, report_w = os.pipe()
        pids = []
        for i, (_, theirs) in enumerate(pairs):
            pid = os.fork()
            if pid == 0:
                status = 1
                try:
                    for j, (mine, other) in enumerate(pairs):
                        mine.close()
                        if j != i:
                            other.close()
                    theirs.setblocking(floor.blocking)
                    cpu0 = time.process_time()
                    floor.participant(theirs, rounds)
                    os.write(report_w, f"{time.process_time() - cpu0!r}\n".encode())
                    status = 0
                except BaseException:
                    traceback.print_exc()
                finally:
                    os._exit(status)
            pids.append(pid)
        socks = [mine for mine, _ in pairs]
        for mine, theirs in pairs:
            theirs.close()
            mine.setblocking(floor.blocking)
        wall0, cpu0 = time.perf_counter(), time.process_time()
        floor.server(socks, rounds)
        wall, cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
        for pid in pids:
            _, status = os.waitpid(pid, 0)
            if status:
                raise SystemExit(f"a participant of the {name} floor failed (status {status})")
        os.close(report_w)
        with os.fdopen(report_r) as reports:
            participant_cpu = [float(line) for line in reports.read().split()]
        for sock in socks:
            sock.close()
    mean = sum(participant_cpu) / len(participant_cpu)
    return rounds / wall, cpu_s / rounds * 1e6, mean / rounds * 1e6


def eventfd_rate(rounds: int) -> tuple[float, float, float]:
    """Round trips per wall second of the blocking ping-pong over a pair of eventfds (how a
    shared-memory ring would wake its peer) instead of a socketpair: what a faster same-host
    transport could save per round at most. CPU figures are not measured (0.0)."""
    grant, done = os.eventfd(0), os.eventfd(0)
    pid = os.fork()
    if pid == 0:
        status = 1
        try:
            for _ in range(rounds):
                os.eventfd_read(grant)
                os.eventfd_write(done, 1)
            status = 0
        finally:
            os._exit(status)
    wall0 = time.perf_counter()
    for _ in range(rounds):
        os.eventfd_write(grant, 1)
        os.eventfd_read(done)
    wall = time.perf_counter() - wall0
    _, status = os.waitpid(pid, 0)
    os.close(grant)
    os.close(done)
    if status:
        raise SystemExit(f"the eventfd ping-pong's participant failed (status {status})")
    return rounds / wall, 0.0, 0.0


def run_side(side: str, fd: int) -> int:
    """One side of a floor (``ping-pong-server``, ``asyncio-participant``...) on the socket
    ``fd``, under callgrind: :data:`WARM` rounds, then :data:`SMALL` and :data:`BIG` counted
    between the marks (the library BENCH_MARKS names), one dump each."""
    name, _, role = side.rpartition("-")
    floor = FLOORS[name]
    sock = socket.socket(fileno=fd)
    sock.setblocking(floor.blocking)
    marks = _Marks(os.environ["BENCH_MARKS"])

    def run(rounds: int) -> None:
        if role == "server":
            floor.server([sock], rounds)
        else:
            floor.participant(sock, rounds)

    marks.start_instrumentation()
    run(WARM)
    for rounds in (SMALL, BIG):
        marks.begin()
        run(rounds)
        marks.end()
    return 0


def lockstep(
    active: int,
    idle: int,
    rounds: int,
    folder: Path,
    root: Path,
    calls: bool = False,
    cpu: int | None = None,
) -> tuple[float, float, float]:
    """Lockstep rounds per wall second with ``active`` busy and ``idle`` idle participants,
    and the CPU microseconds per round of the server and of one active participant (mean);
    every process pinned to ``cpu`` if given.

    With ``calls``: instead, the Python function calls per round (cProfile's count over
    the measured rounds: exact and independent of the machine's load) of the server and of
    one active participant (mean), and 0.0 for the rate.
    """
    url = f"unix://{folder / f'bench-{active}-{idle}.sock'}"
    env = {**os.environ, "PYTHONPATH": str(root)}
    if calls:
        env["BENCH_CALLS"] = "1"
    pin = None if cpu is None else functools.partial(os.sched_setaffinity, 0, {cpu})
    server = subprocess.Popen(
        [sys.executable, "-c", SERVER, url, str(active + idle), str(rounds)],
        cwd=root,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=pin,
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PARTICIPANT, "active" if i < active else "idle"],
            cwd=root,
            env={**env, "EVCLOCK_CLOCK": f"{url}?name=p{i}"},
            stdout=subprocess.PIPE,
            text=True,
            preexec_fn=pin,
        )
        for i in range(active + idle)
    ]
    out, _ = server.communicate(timeout=600)
    reports = [json.loads(proc.communicate(timeout=60)[0]) for proc in procs[:active]]
    for proc in procs[active:]:
        proc.wait(timeout=60)
    result = json.loads(out)
    rounds = result["rounds"]
    if calls:
        mean = sum(report["calls"] for report in reports) / len(reports)
        return 0.0, result["calls"] / rounds, mean / rounds
    participant_cpu = [report["cpu_s"] for report in reports]
    return (
        rounds / result["wall_s"],
        result["cpu_s"] / rounds * 1e6,
        sum(participant_cpu) / len(participant_cpu) / rounds * 1e6,
    )


# ------------------------------------------------------------------------------ callgrind


def valgrind(base: Path) -> list[str]:
    """The command prefix running a process under callgrind, collecting nothing until its
    marks say so, its dumps written to ``base.1``, ``base.2``."""
    return [
        "valgrind",
        "--tool=callgrind",
        "--instr-atstart=no",
        "--collect-atstart=no",
        f"--callgrind-out-file={base}",
    ]


def per_round(base: Path, what: str) -> float:
    """Instructions per steady-state round of the process that dumped to ``base``: (its
    BIG rounds' count - its SMALL rounds' count) / (BIG - SMALL)."""
    totals = []
    for i in (1, 2):
        dump = Path(f"{base}.{i}")
        text = dump.read_text() if dump.exists() else ""
        found = re.search(r"^totals: (\d+)", text, re.MULTILINE)
        if found is None:
            raise SystemExit(f"no totals in callgrind's dump {dump} ({what})")
        totals.append(int(found.group(1)))
    return (totals[1] - totals[0]) / (BIG - SMALL)


def wait_all(procs: list[tuple[str, subprocess.Popen[bytes], Path]]) -> None:
    """Wait for each process; on a failure, stop with its name and its output."""
    for what, proc, log in procs:
        try:
            status = proc.wait(timeout=600)
        except subprocess.TimeoutExpired:
            for _, other, _ in procs:
                other.kill()
            raise SystemExit(
                f"{what}: no end after 600 s; its output:\n{log.read_text()}"
            ) from None
        if status:
            raise SystemExit(f"{what} failed (status {status}):\n{log.read_text()}")


def marks_env(root: Path, marks: str) -> dict[str, str]:
    """The environment of a process counted under callgrind: the marks and the segments."""
    return {
        **os.environ,
        "PYTHONPATH": str(root),
        "PYTHONHASHSEED": "0",  # dict layouts, and so Python code's costs, alike every run
        "BENCH_MARKS": marks,
        "BENCH_DIR": str(HERE),
        "BENCH_SEGMENTS": SEGMENTS,
    }


def spawn_counted(
    what: str, command: list[str], base: Path, **popen: Any
) -> tuple[str, subprocess.Popen[bytes], Path]:
    """Start ``command`` under callgrind (dumps to ``base``, output to ``base.log``)."""
    log = Path(f"{base}.log")
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [*valgrind(base), *command], stdout=out, stderr=subprocess.STDOUT, **popen
        )
    return what, proc, log


def lockstep_instructions(folder: Path, root: Path, marks: str) -> tuple[float, float]:
    """Instructions per steady-state lockstep round with one participant: of the server and
    of the participant, each under callgrind, counting only their measured rounds."""
    url = f"unix://{folder / 'callgrind.sock'}"
    env = marks_env(root, marks)
    server, participant = folder / "lockstep-server.out", folder / "lockstep-participant.out"
    procs = [
        spawn_counted(
            "the lockstep server under callgrind",
            [sys.executable, "-c", SERVER, url, "1", "0"],
            server,
            cwd=root,
            env=env,
        ),
        spawn_counted(
            "the lockstep participant under callgrind",
            [sys.executable, "-c", PARTICIPANT, "active"],
            participant,
            cwd=root,
            env={**env, "EVCLOCK_CLOCK": f"{url}?name=p0"},
        ),
    ]
    wait_all(procs)
    return per_round(server, "lockstep server"), per_round(participant, "lockstep participant")


def floor_instructions(name: str, folder: Path, marks: str) -> tuple[float, float]:
    """Instructions per steady-state round of floor ``name`` (one participant): of its
    server and its participant, each a process of its own under callgrind (``--side``), on
    the two ends of a socketpair."""
    ours, theirs = socket.socketpair()
    procs = []
    for role, sock in (("server", ours), ("participant", theirs)):
        command = [sys.executable, str(Path(__file__).resolve()), "--side", f"{name}-{role}"]
        procs.append(
            spawn_counted(
                f"the {name} {role} under callgrind",
                [*command, "--fd", str(sock.fileno())],
                folder / f"{name}-{role}.out",
                env=marks_env(ROOT, marks),
                pass_fds=[sock.fileno()],
            )
        )
    ours.close()
    theirs.close()
    wait_all(procs)
    return (
        per_round(folder / f"{name}-server.out", f"{name} server"),
        per_round(folder / f"{name}-participant.out", f"{name} participant"),
    )


# ------------------------------------------------------------------------------ KUKA

#: KUKA reaching, its joint controller at a given rate (the scenario's ``control_hz``: a
#: constructor argument, not a ``--param``; and ``--serve`` runs a scenario as registered).
KUKA_AT = '''
"""KUKA reaching with its joint controller at {hz:g} Hz (physics at 240 Hz)."""

from evclock_sims.kuka import KukaReach


class KukaControl(KukaReach):
    """KukaReach, its joint controller at {hz:g} Hz."""

    def __init__(self, world, seed=0):
        super().__init__(world, seed, control_hz={hz!r})
'''


@dataclass
class KukaRun:
    """Physics steps per wall second in-process and split; what differed between them."""

    inprocess: float
    split: float
    differs: list[str]


def kuka_split(folder: Path, root: Path, hz: float) -> KukaRun:
    """KUKA with its joint controller at ``hz``: run in-process (``evclock run``) and split
    (``evclock run --serve ... --remote-controllers`` + ``evclock control``); physics steps
    per wall second of each (from their reports' ``wall_time_s``), and what of the three
    reports differs (final state, sim time, summary, loop ticks: all bit-identical in a
    correct split run)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    scenario_file = folder / f"kuka_control_{hz:g}hz.py"
    scenario_file.write_text(KUKA_AT.format(hz=hz))
    spec = f"{scenario_file}:KukaControl"
    inproc, served, joined = (folder / f"kuka-{hz:g}-{n}.json" for n in ("in", "srv", "ctl"))

    def check(what: str, status: int, output: str) -> None:
        if status:
            raise SystemExit(f"KUKA at {hz:g} Hz, {what}: status {status}\n{output}")

    def run_cli(what: str, *args: str) -> None:
        done = subprocess.run(
            [*CLI, *args], cwd=root, env=env, capture_output=True, text=True, timeout=600
        )
        check(what, done.returncode, done.stdout + done.stderr)

    run_cli("in-process run", "run", spec, "--quiet", "--json", str(inproc))
    url = f"unix://{folder / f'kuka-{hz:g}.sock'}"
    log = folder / "kuka-served.log"
    with log.open("wb") as out:
        server = subprocess.Popen(
            [*CLI, "run", spec, "--quiet", "--serve", url, "--remote-controllers", "--json",
             str(served)],
            cwd=root,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
    run_cli("evclock control", "control", spec, "--quiet", "--clock", url, "--json", str(joined))
    check("evclock run --serve", server.wait(timeout=600), log.read_text())
    reports = [json.loads(path.read_text()) for path in (inproc, served, joined)]
    rates = [r["sim_time_s"] * 240 / r["wall_time_s"] for r in reports[:2]]
    reference = reports[0]
    differs = []
    for key in ("final_state", "sim_time_s", "summary"):
        if any(r[key] != reference[key] for r in reports[1:]):
            differs.append(key)
    ticks = [[loop["stats"]["ticks"] for loop in r["loops"]] for r in reports[:2]]
    if ticks[0] != ticks[1]:
        differs.append("loop ticks")
    return KukaRun(rates[0], rates[1], differs)


# ------------------------------------------------------------------------------ targets


@dataclass
class Target(instructions.Target):
    """A target of the project, met or not by a figure of this run: a ratio, a count or a
    yes/no."""

    unit: str = "x"  # "x" (a ratio), "instr" (a count) or "yes" (1.0: yes, 0.0: no)

    def line(self) -> str:
        sign = ">=" if self.at_least else "<="
        if self.unit == "x":
            value, limit = f"{self.value:.3f}x", f"{sign} {self.limit:.2f}x"
        elif self.unit == "instr":
            value, limit = f"{self.value:,.0f}", f"{sign} {self.limit:,.0f}"
        else:
            value, limit = ("yes" if self.value else "no"), "   yes"
        verdict = "met" if self.met else "NOT MET"
        return f"  {self.what:<70}{value:>9}  {limit:<9}  {verdict}"


def variant_label(active: int, idle: int) -> str:
    """How the output names a lockstep variant."""
    if idle:
        return f"{active} active + {idle} idle"
    return f"{active} participant" + ("s" if active > 1 else "")


def keep_best(results: dict[str, Any], key: str, figures: tuple[float, float, float]) -> None:
    """Keep ``figures`` (rounds/s, server and participant CPU us per round) under ``key``
    (``..._rounds_per_s``) if their rate is the best yet."""
    rate, server_us, participant_us = figures
    if rate > results.get(key, 0.0):
        results[key] = rate
        results[key.replace("rounds_per_s", "server_cpu_us")] = server_us
        results[key.replace("rounds_per_s", "participant_cpu_us")] = participant_us


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5000)
    parser.add_argument("--participants", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--kuka", action=argparse.BooleanOptionalAction, default=True)
    for flag, also in (
        ("--instructions", "count instructions per round under callgrind (needs valgrind, gcc)"),
        ("--pinned", "measure 1 participant and its floors with every process on one CPU"),
        ("--calls", "count Python function calls per round (exact, load-independent)"),
    ):
        parser.add_argument(
            flag, action=argparse.BooleanOptionalAction, default=True, help="also " + also
        )
    parser.add_argument(
        "--cpu", type=int, default=None, help="the CPU of --pinned (default: the last allowed)"
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--against", type=Path, default=None, help="another evclock checkout, measured alike"
    )
    parser.add_argument("--side", help=argparse.SUPPRESS)
    parser.add_argument("--fd", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.side is not None:
        raise SystemExit(run_side(args.side, args.fd))
    if args.instructions and (shutil.which("valgrind") is None or shutil.which("gcc") is None):
        parser.error(
            "--instructions counts under callgrind: it needs valgrind and gcc (apt-get install "
            "valgrind gcc), or pass --no-instructions"
        )
    started = time.monotonic()
    checkouts = [("", ROOT)]
    if args.against is not None:
        if not (args.against / "evclock" / "__init__.py").is_file():
            parser.error(f"--against {args.against}: not an evclock checkout")
        checkouts.append(("against_", args.against.resolve()))
    cpu = None
    if args.pinned:
        allowed = sorted(os.sched_getaffinity(0))
        cpu = allowed[-1] if args.cpu is None else args.cpu
        if cpu not in allowed:
            parser.error(f"--cpu {cpu}: not one this process may run on ({allowed})")
    widths = sorted({n for n in args.participants if n > 1})
    results: dict[str, Any] = {}
    variants = [(f"lockstep_{n}_rounds_per_s", n, 0) for n in args.participants]
    variants.append(("lockstep_1_active_15_idle_rounds_per_s", 1, 15))
    kuka: dict[str, list[KukaRun]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        floor_rounds = args.rounds * 4
        for _ in range(args.repeat):
            keep_best(results, "ping_pong_rounds_per_s", floor_rate("ping-pong", 1, floor_rounds))
            keep_best(results, "eventfd_ping_pong_rounds_per_s", eventfd_rate(floor_rounds))
            for width in widths:
                keep_best(
                    results,
                    f"fan_out_{width}_rounds_per_s",
                    floor_rate("fan-out", width, max(args.rounds, floor_rounds // width)),
                )
            keep_best(results, "asyncio_floor_rounds_per_s", floor_rate("asyncio", 1, floor_rounds))
            if cpu is not None:
                keep_best(
                    results,
                    "ping_pong_pinned_rounds_per_s",
                    floor_rate("ping-pong", 1, floor_rounds, cpu),
                )
                keep_best(
                    results,
                    "asyncio_floor_pinned_rounds_per_s",
                    floor_rate("asyncio", 1, floor_rounds, cpu),
                )
            for name, active, idle in variants:
                for prefix, root in checkouts:
                    keep_best(
                        results, prefix + name, lockstep(active, idle, args.rounds, folder, root)
                    )
            if cpu is not None:
                for prefix, root in checkouts:
                    keep_best(
                        results,
                        f"{prefix}lockstep_1_pinned_rounds_per_s",
                        lockstep(1, 0, args.rounds, folder, root, cpu=cpu),
                    )
            if args.kuka:
                for hz in KUKA_CONTROL_HZ:
                    for prefix, root in checkouts:
                        run = kuka_split(folder, root, hz)
                        kuka.setdefault(f"{prefix}kuka_{hz:g}hz", []).append(run)
        for key, runs in kuka.items():
            results[f"{key}_inprocess_steps_per_s"] = inproc = max(r.inprocess for r in runs)
            results[f"{key}_split_steps_per_s"] = split = max(r.split for r in runs)
            results[f"{key}_split_ratio"] = split / inproc
            differs = sorted({what for r in runs for what in r.differs})
            results[f"{key}_split_bit_identical"] = not differs
            results[f"{key}_split_differs"] = differs
        for prefix, _root in checkouts if args.kuka else ():  # the keys of earlier versions
            for figure in ("inprocess_steps_per_s", "split_steps_per_s", "split_ratio"):
                results[f"{prefix}kuka_{figure}"] = results[f"{prefix}kuka_100hz_{figure}"]
        if args.instructions:
            marks = build_marks(tmp)
            for name in ("ping-pong", "asyncio"):
                server, participant = floor_instructions(name, folder, marks)
                key = "ping_pong" if name == "ping-pong" else "asyncio_floor"
                results[f"{key}_server_instructions"] = server
                results[f"{key}_participant_instructions"] = participant
            for prefix, root in checkouts:
                server, participant = lockstep_instructions(folder, root, marks)
                results[f"{prefix}lockstep_1_server_instructions"] = server
                results[f"{prefix}lockstep_1_participant_instructions"] = participant

    base = results["ping_pong_round_trips_per_s"] = results["ping_pong_rounds_per_s"]
    print(
        f"python {sys.version.split()[0]}; wall figures: best of {args.repeat}, variants "
        f"interleaved; a round: a 9-byte GRANT out, a 17-byte DONE back"
    )
    print(f"ping-pong (2 processes, blocking): {base:,.0f} round trips/s")
    eventfd = results["eventfd_ping_pong_rounds_per_s"]
    print(
        f"ping-pong over eventfds instead of a socket (a shared-memory ring's wake-up): "
        f"{eventfd:,.0f} round trips/s ({1e6 / eventfd:.1f} us per round trip; over the socket "
        f"{1e6 / base:.1f} us)"
    )
    if cpu is not None:
        print(
            f"ping-pong, every process on CPU {cpu}: "
            f"{results['ping_pong_pinned_rounds_per_s']:,.0f} round trips/s"
        )
    for width in widths:
        print(
            f"fan-out ping-pong (1 blocking process, {width} participant processes): "
            f"{results[f'fan_out_{width}_rounds_per_s']:,.0f} rounds/s"
        )
    floor = results["asyncio_floor_rounds_per_s"]
    print(
        f"asyncio floor (no evclock: a reader callback answers, a task is woken per round): "
        f"{floor:,.0f} rounds/s ({floor / base:.2f} x ping-pong); CPU per round: answering "
        f"side {results['asyncio_floor_server_cpu_us']:.0f} us, task side "
        f"{results['asyncio_floor_participant_cpu_us']:.0f} us"
    )
    if cpu is not None:
        pinned_floor = results["asyncio_floor_pinned_rounds_per_s"]
        pinned_base = results["ping_pong_pinned_rounds_per_s"]
        print(
            f"asyncio floor, every process on CPU {cpu}: {pinned_floor:,.0f} rounds/s "
            f"({pinned_floor / pinned_base:.2f} x the pinned ping-pong)"
        )

    def floor_of(active: int, idle: int) -> tuple[float, str]:
        if active + idle == 1 or idle:
            return base, "ping-pong"
        return results[f"fan_out_{active}_rounds_per_s"], f"fan-out ping-pong of width {active}"

    targets: list[tuple[Path, list[Target]]] = []
    for prefix, root in checkouts:
        print(f"\n{root}:")
        mine: list[Target] = []
        for name, active, idle in variants:
            key = prefix + name
            label = variant_label(active, idle)
            rate = results[key]
            reference, what = floor_of(active, idle)
            server_us = results[key.replace("rounds_per_s", "server_cpu_us")]
            participant_us = results[key.replace("rounds_per_s", "participant_cpu_us")]
            print(
                f"lockstep, {label}: {rate:,.0f} rounds/s ({rate / reference:.2f} x {what}); "
                f"CPU per round: server {server_us:.0f} us, each active participant "
                f"{participant_us:.0f} us"
            )
            if not idle:
                mine.append(
                    Target(
                        f"lockstep rounds/s, {label} / {what}",
                        rate / reference,
                        ROUNDS_TARGET,
                        at_least=True,
                    )
                )
        if cpu is not None:
            key = f"{prefix}lockstep_1_pinned_rounds_per_s"
            rate = results[key]
            reference = results["ping_pong_pinned_rounds_per_s"]
            print(
                f"lockstep, 1 participant, every process on CPU {cpu}: {rate:,.0f} rounds/s "
                f"({rate / reference:.2f} x the pinned ping-pong); CPU per round: server "
                f"{results[key.replace('rounds_per_s', 'server_cpu_us')]:.0f} us, participant "
                f"{results[key.replace('rounds_per_s', 'participant_cpu_us')]:.0f} us"
            )
            mine.append(
                Target(
                    "lockstep rounds/s, 1 participant / ping-pong, all on one CPU",
                    rate / reference,
                    ROUNDS_TARGET,
                    at_least=True,
                )
            )
        if args.instructions:
            server = results[f"{prefix}lockstep_1_server_instructions"]
            participant = results[f"{prefix}lockstep_1_participant_instructions"]
            mine.append(
                Target(
                    "instructions per lockstep round, server + 1 participant",
                    server + participant,
                    INSTRUCTIONS_TARGET,
                    unit="instr",
                )
            )
        for hz in KUKA_CONTROL_HZ if args.kuka else ():
            key = f"{prefix}kuka_{hz:g}hz"
            ratio = results[f"{key}_split_ratio"]
            differs = results[f"{key}_split_differs"]
            print(
                f"KUKA, physics 240 Hz, control {hz:g} Hz: in-process "
                f"{results[f'{key}_inprocess_steps_per_s']:,.0f} steps/s, controllers in "
                f"another process {results[f'{key}_split_steps_per_s']:,.0f} steps/s: ratio "
                f"{ratio:.2f}; split run vs in-process: "
                + (
                    "final state, sim time, summary and loop ticks bit-identical"
                    if not differs
                    else f"{', '.join(differs)} DIFFER"
                )
            )
            mine.append(
                Target(
                    f"KUKA split / in-process steps/s, control {hz:g} Hz",
                    ratio,
                    KUKA_TARGET,
                    at_least=True,
                )
            )
            mine.append(
                Target(
                    f"KUKA split trajectory bit-identical to in-process, control {hz:g} Hz",
                    float(not differs),
                    1.0,
                    at_least=True,
                    unit="yes",
                )
            )
        targets.append((root, mine))

    if args.instructions:
        print(
            f"\ninstructions per round under callgrind (each process counts only its measured "
            f"rounds: ({BIG} rounds - {SMALL} rounds) / {BIG - SMALL}; 1 participant)"
        )
        print(f"  {'':<44}{'server':>10}{'participant':>13}{'sum':>10}{'x ping-pong':>13}")
        rows = [
            ("blocking ping-pong", "ping_pong"),
            ("asyncio floor (a reader callback, a task)", "asyncio_floor"),
        ]
        rows += [(f"evclock lockstep, {root}", f"{prefix}lockstep_1") for prefix, root in checkouts]
        for label, key in rows:
            server = results[f"{key}_server_instructions"]
            participant = results[f"{key}_participant_instructions"]
            total = results[f"{key}_instructions"] = server + participant
            print(
                f"  {label:<44}{server:>10,.0f}{participant:>13,.0f}{total:>10,.0f}"
                f"{total / results['ping_pong_instructions']:>12.2f}x"
            )

    if args.calls:
        print("\nPython function calls per round (cProfile count: exact, load-independent):")
        with tempfile.TemporaryDirectory() as calls_dir:
            for name, active, idle in variants:
                for prefix, root in checkouts:
                    _, server_calls, participant_calls = lockstep(
                        active, idle, min(args.rounds, 1000), Path(calls_dir), root, calls=True
                    )
                    key = prefix + name.replace("rounds_per_s", "")
                    results[key + "server_calls"] = server_calls
                    results[key + "participant_calls"] = participant_calls
                    label = variant_label(active, idle)
                    print(
                        f"{root}: {label}: server {server_calls:.0f}, each active participant "
                        f"{participant_calls:.0f}"
                    )

    results["targets"] = []
    for root, mine in targets:
        print(f"\ntargets ({root}, same run)")
        for target in mine:
            print(target.line())
            results["targets"].append(
                {
                    "checkout": str(root),
                    "what": target.what,
                    "value": target.value,
                    "limit": target.limit,
                    "at_least": target.at_least,
                    "met": target.met,
                }
            )
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
