"""Sim time across processes: lockstep rounds per second, and KUKA split across processes.

Usage: python benchmarks/remote_lockstep.py [--rounds 5000] [--participants 1 4 16]
                                            [--repeat 3] [--kuka/--no-kuka] [--json out.json]

Measured in one run, each against a baseline of the same run:

* **ping-pong**: a bare blocking round trip between two Python processes over a Unix
  socketpair (send 9 bytes, answer 17): the floor of any lockstep round between processes.
* **lockstep rounds/s** with N participant processes over a Unix socket: the simulation
  (virtual time) serves; each participant sleeps 1 ms of sim time ``--rounds`` times, so
  every round grants all N and waits for all N DONEs. Reported as rounds per wall second and
  as a ratio of the ping-pong rate.
* **idle participants cost nothing**: 1 active participant plus 15 that sleep an hour of sim
  time (no deadline due in any measured round); compare with the 1-participant figure.
* **KUKA split**: ``evclock run kuka --serve ... --remote-controllers`` with ``evclock control
  kuka`` in another process, against the in-process ``evclock run kuka``; physics steps per
  wall second of each (from their reports' ``wall_time_s``) and the ratio (target >= 0.5).

Each figure is the best of ``--repeat`` runs, variants interleaved so that load from elsewhere
hits all alike. Wall time is what a round costs here, so a loaded machine lowers every
figure; the ratios to the same-run baselines are the comparable numbers.
"""

from __future__ import annotations

import argparse
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
CLI = [sys.executable, "-c", "from evclock._cli import main; main()"]

SERVER = textwrap.dedent(
    """
    import json, sys, time, evclock
    async def main():
        count, rounds = int(sys.argv[2]), int(sys.argv[3])
        async with evclock.serve(sys.argv[1]) as server:
            await server.wait_for_participants(count=count)
            wall0 = time.perf_counter()
            await evclock.clock().sleep(rounds / 1000)  # `rounds` rounds of 1 ms
            wall = time.perf_counter() - wall0
        print(json.dumps({"rounds": rounds, "wall_s": wall}))
    evclock.run(main())
    """
)
# Active participants sleep 1 ms at a time (past the measured rounds: the server stops first
# and they end with ClockLost, as expected); idle ones sleep an hour: no deadline is due.
PARTICIPANT = textwrap.dedent(
    """
    import sys, evclock
    async def main():
        clock = evclock.clock()
        if sys.argv[1] == "idle":
            await clock.sleep(3600)
        while True:
            await clock.sleep(0.001)
    try:
        evclock.run(main())
    except evclock.ClockLost:
        pass
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


def lockstep(active: int, idle: int, rounds: int, folder: Path) -> float:
    """Lockstep rounds per wall second with ``active`` busy and ``idle`` idle participants."""
    url = f"unix://{folder / f'bench-{active}-{idle}.sock'}"
    server = subprocess.Popen(
        [sys.executable, "-c", SERVER, url, str(active + idle), str(rounds)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PARTICIPANT, "active" if i < active else "idle"],
            cwd=ROOT,
            env={**os.environ, "EVCLOCK_CLOCK": f"{url}?name=p{i}"},
        )
        for i in range(active + idle)
    ]
    out, _ = server.communicate(timeout=600)
    for proc in procs:
        proc.wait(timeout=60)
    result = json.loads(out)
    return float(result["rounds"] / result["wall_s"])


def kuka_split(folder: Path) -> tuple[float, float]:
    """Physics steps per wall second: (in-process, split across two processes)."""
    inproc = folder / "inproc.json"
    subprocess.run(
        [*CLI, "run", "kuka", "--quiet", "--json", str(inproc)],
        cwd=ROOT,
        check=True,
        capture_output=True,
        timeout=600,
    )
    url = f"unix://{folder / 'kuka.sock'}"
    served = folder / "served.json"
    server = subprocess.Popen(
        [*CLI, "run", "kuka", "--quiet", "--serve", url, "--remote-controllers", "--json",
         str(served)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    subprocess.run(
        [*CLI, "control", "kuka", "--quiet", "--clock", url],
        cwd=ROOT,
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
    args = parser.parse_args()
    results: dict[str, float] = {}
    variants = [(f"lockstep_{n}_rounds_per_s", n, 0) for n in args.participants]
    variants.append(("lockstep_1_active_15_idle_rounds_per_s", 1, 15))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for _ in range(args.repeat):
            best = results.get("ping_pong_round_trips_per_s", 0.0)
            results["ping_pong_round_trips_per_s"] = max(best, ping_pong(args.rounds * 4))
            for key, active, idle in variants:
                rate = lockstep(active, idle, args.rounds, folder)
                results[key] = max(results.get(key, 0.0), rate)
            if args.kuka:
                inproc, split = kuka_split(folder)
                if split / inproc > results.get("kuka_split_ratio", 0.0):
                    results.update(
                        kuka_inprocess_steps_per_s=inproc,
                        kuka_split_steps_per_s=split,
                        kuka_split_ratio=split / inproc,
                    )
    base = results["ping_pong_round_trips_per_s"]
    print(f"baseline ping-pong (2 processes, blocking): {base:,.0f} round trips/s")
    for key, active, idle in variants:
        label = f"{active} participant(s)" if not idle else f"{active} active + {idle} idle"
        rate = results[key]
        print(f"lockstep, {label}: {rate:,.0f} rounds/s ({rate / base:.2f} x ping-pong)")
    if args.kuka:
        print(
            f"KUKA: in-process {results['kuka_inprocess_steps_per_s']:,.0f} steps/s, "
            f"controllers in another process {results['kuka_split_steps_per_s']:,.0f} "
            f"steps/s: ratio {results['kuka_split_ratio']:.2f}"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
