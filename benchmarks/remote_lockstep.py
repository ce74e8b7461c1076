"""Sim time across processes: lockstep rounds per second, and KUKA split across processes.

Usage: python benchmarks/remote_lockstep.py [--rounds 5000] [--participants 1 4 16]
                                            [--repeat 3] [--kuka/--no-kuka] [--json out.json]
                                            [--against OTHER_CHECKOUT] [--calls/--no-calls]

Measured in one run, each against a baseline of the same run:

* **ping-pong**: a bare blocking round trip between two Python processes over a Unix
  socketpair (send 9 bytes, answer 17): the floor of any lockstep round between processes.
* **asyncio floor**: the same exchange with no evclock at all, shaped like a lockstep round
  of this design: one process answers in a stock asyncio loop's reader callback (the
  server), the other wakes a stock asyncio task per round through a future its reader
  callback resolves, and the task sends (the participant's ``await clock.sleep``). What a
  round costs in asyncio alone, before evclock does any work: the ceiling of any design
  in which the participant is an asyncio task.
* **lockstep rounds/s** with N participant processes over a Unix socket: the simulation
  (virtual time) serves; each participant sleeps 1 ms of sim time ``--rounds`` times, so
  every round grants all N and waits for all N DONEs. Reported as rounds per wall second and
  as a ratio of the ping-pong rate, with the CPU time per round of the server and of each
  active participant (``time.process_time`` over the measured rounds: what a round costs,
  much less sensitive to the machine's load than wall time).
* **idle participants cost nothing**: 1 active participant plus 15 that sleep an hour of sim
  time (no deadline due in any measured round); compare with the 1-participant figure.
* **KUKA split**: ``evclock run kuka --serve ... --remote-controllers`` with ``evclock control
  kuka`` in another process, against the in-process ``evclock run kuka``; physics steps per
  wall second of each (from their reports' ``wall_time_s``) and the ratio (target >= 0.5).

* **Python calls per round** (``--calls``, default on): the same rounds under cProfile,
  counting the function calls of the server and of an active participant per round. Exact
  and independent of the machine's load (instruction counts under callgrind are too, but
  take minutes per run on a shared 2-core machine); what a change removed, call by call.

``--against DIR`` measures another checkout of evclock (``git worktree add /tmp/base main``)
in the same run, interleaved with this one: before/after figures of a change.

Each figure is the best of ``--repeat`` runs, variants interleaved so that load from elsewhere
hits all alike. Wall time is what a round costs here, so a loaded machine lowers every
figure; the ratios to the same-run baselines are the comparable numbers.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "from evclock.tools._cli import main; main()"]

SERVER = textwrap.dedent(
    """
    import cProfile, json, os, pstats, sys, time, evclock
    profile = cProfile.Profile() if os.environ.get("BENCH_CALLS") else None
    async def main():
        count, rounds = int(sys.argv[2]), int(sys.argv[3])
        async with evclock.remote.serve(sys.argv[1]) as server:
            await server.wait_for_participants(count=count)
            wall0, cpu0 = time.perf_counter(), time.process_time()
            if profile:
                profile.enable()
            await evclock.clock().sleep(rounds / 1000)  # `rounds` rounds of 1 ms
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
PARTICIPANT = textwrap.dedent(
    """
    import cProfile, json, os, pstats, sys, time, evclock
    profile = cProfile.Profile() if os.environ.get("BENCH_CALLS") else None
    cpu0 = None
    async def main():
        global cpu0
        clock = evclock.clock()
        if sys.argv[1] == "idle":
            await clock.sleep(3600)
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


def ping_pong(rounds: int) -> float:
    """Round trips per second of a bare blocking exchange between two processes."""
    a, b = socket.socketpair()
    pid = os.fork()
    if pid == 0:
        a.close()
        for _ in range(rounds):
            b.recv(64)
            b.send(b"d" * 17)
        os._exit(0)
    b.close()
    t0 = time.perf_counter()
    for _ in range(rounds):
        a.send(b"g" * 9)
        a.recv(64)
    elapsed = time.perf_counter() - t0
    os.waitpid(pid, 0)
    a.close()
    return rounds / elapsed


def asyncio_floor(rounds: int) -> tuple[float, float, float]:
    """Rounds per second of the asyncio-only floor, and the CPU microseconds per round of
    the answering side (a reader callback) and of the task side."""

    def answer(sock: socket.socket) -> None:  # the server: a reader callback answers
        loop = asyncio.new_event_loop()
        finished = loop.create_future()
        seen = 0

        def on_readable() -> None:
            nonlocal seen
            sock.recv(64)
            seen += 1
            sock.send(b"g" * 9)
            if seen == rounds:
                loop.remove_reader(sock)
                finished.set_result(None)

        loop.add_reader(sock, on_readable)
        loop.run_until_complete(finished)
        loop.close()

    def work(sock: socket.socket) -> None:  # the participant: a task woken per round
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
                sock.send(b"d" * 17)
                await waiter[0]
            loop.remove_reader(sock)

        loop.run_until_complete(main())
        loop.close()

    a, b = socket.socketpair()
    a.setblocking(False)
    b.setblocking(False)
    report_r, report_w = os.pipe()
    pid = os.fork()
    if pid == 0:
        a.close()
        cpu0 = time.process_time()
        answer(b)
        os.write(report_w, str(time.process_time() - cpu0).encode())
        os._exit(0)
    b.close()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    work(a)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    os.waitpid(pid, 0)
    server_cpu = float(os.read(report_r, 64))
    for fd in (report_r, report_w):
        os.close(fd)
    a.close()
    return rounds / wall, server_cpu / rounds * 1e6, cpu / rounds * 1e6


def lockstep(
    active: int, idle: int, rounds: int, folder: Path, root: Path, calls: bool = False
) -> tuple[float, float, float]:
    """Lockstep rounds per wall second with ``active`` busy and ``idle`` idle participants,
    and the CPU microseconds per round of the server and of one active participant (mean).

    With ``calls``: instead, the Python function calls per round (cProfile's count over
    the measured rounds: exact and independent of the machine's load) of the server and of
    one active participant (mean), and 0.0 for the rate.
    """
    url = f"unix://{folder / f'bench-{active}-{idle}.sock'}"
    env = {**os.environ, "PYTHONPATH": str(root)}
    if calls:
        env["BENCH_CALLS"] = "1"
    server = subprocess.Popen(
        [sys.executable, "-c", SERVER, url, str(active + idle), str(rounds)],
        cwd=root,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PARTICIPANT, "active" if i < active else "idle"],
            cwd=root,
            env={**env, "EVCLOCK_CLOCK": f"{url}?name=p{i}"},
            stdout=subprocess.PIPE,
            text=True,
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


def kuka_split(folder: Path, root: Path) -> tuple[float, float]:
    """Physics steps per wall second: (in-process, split across two processes)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    inproc = folder / "inproc.json"
    subprocess.run(
        [*CLI, "run", "kuka", "--quiet", "--json", str(inproc)],
        cwd=root,
        env=env,
        check=True,
        capture_output=True,
        timeout=600,
    )
    url = f"unix://{folder / 'kuka.sock'}"
    served = folder / "served.json"
    server = subprocess.Popen(
        [*CLI, "run", "kuka", "--quiet", "--serve", url, "--remote-controllers", "--json",
         str(served)],
        cwd=root,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    subprocess.run(
        [*CLI, "control", "kuka", "--quiet", "--clock", url],
        cwd=root,
        env=env,
        check=True,
        capture_output=True,
        timeout=600,
    )
    server.wait(timeout=600)
    rates = []
    for report_path in (inproc, served):
        report = json.loads(report_path.read_text())
        rates.append(report["sim_time_s"] * 240 / report["wall_time_s"])
    return rates[0], rates[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5000)
    parser.add_argument("--participants", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--kuka", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--calls",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also count Python function calls per round (exact, load-independent)",
    )
    parser.add_argument(
        "--against", type=Path, default=None, help="another evclock checkout, measured alike"
    )
    args = parser.parse_args()
    checkouts = [("", ROOT)]
    if args.against is not None:
        if not (args.against / "evclock" / "__init__.py").is_file():
            parser.error(f"--against {args.against}: not an evclock checkout")
        checkouts.append(("against_", args.against.resolve()))
    results: dict[str, float] = {}
    variants = [(f"lockstep_{n}_rounds_per_s", n, 0) for n in args.participants]
    variants.append(("lockstep_1_active_15_idle_rounds_per_s", 1, 15))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for _ in range(args.repeat):
            best = results.get("ping_pong_round_trips_per_s", 0.0)
            results["ping_pong_round_trips_per_s"] = max(best, ping_pong(args.rounds * 4))
            rate, server_us, participant_us = asyncio_floor(args.rounds * 4)
            if rate > results.get("asyncio_floor_rounds_per_s", 0.0):
                results["asyncio_floor_rounds_per_s"] = rate
                results["asyncio_floor_server_cpu_us"] = server_us
                results["asyncio_floor_participant_cpu_us"] = participant_us
            for name, active, idle in variants:
                for prefix, root in checkouts:
                    key = prefix + name
                    rate, server_us, participant_us = lockstep(
                        active, idle, args.rounds, folder, root
                    )
                    if rate > results.get(key, 0.0):
                        results[key] = rate
                        results[key.replace("rounds_per_s", "server_cpu_us")] = server_us
                        results[key.replace("rounds_per_s", "participant_cpu_us")] = participant_us
            if args.kuka:
                for prefix, root in checkouts:
                    inproc, split = kuka_split(folder, root)
                    if split / inproc > results.get(f"{prefix}kuka_split_ratio", 0.0):
                        results[f"{prefix}kuka_inprocess_steps_per_s"] = inproc
                        results[f"{prefix}kuka_split_steps_per_s"] = split
                        results[f"{prefix}kuka_split_ratio"] = split / inproc
    base = results["ping_pong_round_trips_per_s"]
    print(f"baseline ping-pong (2 processes, blocking): {base:,.0f} round trips/s")
    floor = results["asyncio_floor_rounds_per_s"]
    print(
        f"asyncio floor (no evclock: a reader callback answers, a task is woken per round): "
        f"{floor:,.0f} rounds/s ({floor / base:.2f} x ping-pong); CPU per round: answering "
        f"side {results['asyncio_floor_server_cpu_us']:.0f} us, task side "
        f"{results['asyncio_floor_participant_cpu_us']:.0f} us"
    )
    for prefix, root in checkouts:
        print(f"\n{root}:")
        for name, active, idle in variants:
            key = prefix + name
            label = f"{active} participant(s)" if not idle else f"{active} active + {idle} idle"
            rate = results[key]
            server_us = results[key.replace("rounds_per_s", "server_cpu_us")]
            participant_us = results[key.replace("rounds_per_s", "participant_cpu_us")]
            print(
                f"lockstep, {label}: {rate:,.0f} rounds/s ({rate / base:.2f} x ping-pong); "
                f"CPU per round: server {server_us:.0f} us, each active participant "
                f"{participant_us:.0f} us"
            )
        if args.kuka:
            print(
                f"KUKA: in-process {results[f'{prefix}kuka_inprocess_steps_per_s']:,.0f} "
                f"steps/s, controllers in another process "
                f"{results[f'{prefix}kuka_split_steps_per_s']:,.0f} steps/s: ratio "
                f"{results[f'{prefix}kuka_split_ratio']:.2f}"
            )
    if args.calls:
        print("\nPython function calls per round (cProfile count: exact, load-independent):")
        calls_dir = tempfile.TemporaryDirectory()
        folder_for_calls = Path(calls_dir.name)
        for name, active, idle in variants:
            for prefix, root in checkouts:
                _, server_calls, participant_calls = lockstep(
                    active, idle, min(args.rounds, 1000), folder_for_calls, root, calls=True
                )
                key = prefix + name.replace("rounds_per_s", "")
                results[key + "server_calls"] = server_calls
                results[key + "participant_calls"] = participant_calls
                label = f"{active} participant(s)" if not idle else f"{active} active + {idle} idle"
                print(
                    f"{root}: {label}: server {server_calls:.0f}, each active participant "
                    f"{participant_calls:.0f}"
                )
        calls_dir.cleanup()
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
