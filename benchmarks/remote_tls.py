"""The lockstep round over TLS beside plain TCP and a Unix socket, in the same run.

Usage: python benchmarks/remote_tls.py [--rounds 3000] [--repeat 3]
           [--instructions/--no-instructions] [--json out.json]

One simulation serving one lockstep participant that sleeps 1 ms of sim time per round
(the programs of ``remote_lockstep.py``), over three transports on this machine:
``unix://`` (the default), ``tcp://127.0.0.1`` and ``tls://127.0.0.1`` (TLS 1.3, a
certificate made for the run with ``trustme``, the participant verifying it against its CA).
The token's handshake is the same on TCP and TLS; a round is a 9-byte GRANT out and a
17-byte DONE back, each one TLS record on ``tls://``.

For each transport: rounds per wall second (best of ``--repeat``, the transports
interleaved so that load from elsewhere hits all alike) and the CPU time per round of the
server and of the participant (``time.process_time`` over the measured rounds); with
``--instructions`` (default on; needs valgrind and gcc) the instructions per round of each
side under callgrind (only the measured rounds counted: ``remote_lockstep.py``'s marks,
(600 - 300 rounds) / 300), exact and independent of the machine's load. Every figure is
also given as a ratio to plain TCP measured in the same run: what TLS costs a round.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import remote_lockstep as rl
from instructions import build_marks

ROOT = Path(__file__).resolve().parent.parent
TRANSPORTS = ("unix", "tcp", "tls")
#: remote_lockstep's server, serving with the options BENCH_SERVE names (token, certificate).
SERVER = rl.SERVER.replace(
    "evclock.remote.serve(sys.argv[1])",
    'evclock.remote.serve(sys.argv[1], **json.loads(os.environ["BENCH_SERVE"]))',
)
assert SERVER != rl.SERVER, "remote_lockstep.SERVER no longer calls serve(sys.argv[1])"


@dataclass
class Transport:
    """Where the server listens, how the participant joins, what serve() is given."""

    name: str
    serve_url: str
    join_url: str
    options: dict[str, str] = field(default_factory=dict)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def transport(name: str, folder: Path, token: str) -> Transport:
    """A fresh endpoint of ``name`` (a new port for every run)."""
    if name == "unix":
        url = f"unix://{folder / 'bench-tls.sock'}"
        return Transport(name, url, f"{url}?name=p0")
    url = f"{name}://127.0.0.1:{free_port()}"
    if name == "tcp":
        return Transport(name, url, f"{url}?token={token}&name=p0", {"token": token})
    return Transport(
        name,
        url,
        f"{url}?token={token}&name=p0&tls_ca={folder / 'ca.pem'}",
        {"token": token, "tls_cert": str(folder / "cert.pem"), "tls_key": str(folder / "key.pem")},
    )


def make_certificates(folder: Path) -> None:
    """A CA and a certificate for 127.0.0.1 signed by it (``trustme``)."""
    try:
        import trustme
    except ImportError:
        raise SystemExit(
            "this benchmark makes its certificates with trustme: pip install trustme"
        ) from None
    ca = trustme.CA()
    leaf = ca.issue_cert("127.0.0.1")
    ca.cert_pem.write_to_path(str(folder / "ca.pem"))
    leaf.private_key_pem.write_to_path(str(folder / "key.pem"))
    leaf.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))


def lockstep(where: Transport, rounds: int) -> tuple[float, float, float]:
    """Rounds per wall second over ``where``, and the CPU microseconds per round of the
    server and of the participant."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "BENCH_SERVE": json.dumps(where.options)}
    env.pop("BENCH_CALLS", None)
    server = subprocess.Popen(
        [sys.executable, "-c", SERVER, where.serve_url, "1", str(rounds)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    participant = subprocess.Popen(
        [sys.executable, "-c", rl.PARTICIPANT, "active"],
        cwd=ROOT,
        env={**env, "EVCLOCK_CLOCK": where.join_url},
        stdout=subprocess.PIPE,
        text=True,
    )
    out, _ = server.communicate(timeout=600)
    report = json.loads(participant.communicate(timeout=60)[0])
    if server.returncode:
        raise SystemExit(f"the {where.name} server failed (status {server.returncode})")
    result = json.loads(out)
    done = result["rounds"]
    return (
        done / result["wall_s"],
        result["cpu_s"] / done * 1e6,
        report["cpu_s"] / done * 1e6,
    )


def instructions(where: Transport, folder: Path, marks: str) -> tuple[float, float]:
    """Instructions per steady-state round over ``where``: server, participant."""
    env = {**rl.marks_env(ROOT, marks), "BENCH_SERVE": json.dumps(where.options)}
    server, participant = folder / f"{where.name}-server.out", folder / f"{where.name}-part.out"
    procs = [
        rl.spawn_counted(
            f"the {where.name} server under callgrind",
            [sys.executable, "-c", SERVER, where.serve_url, "1", "0"],
            server,
            cwd=ROOT,
            env=env,
        ),
        rl.spawn_counted(
            f"the {where.name} participant under callgrind",
            [sys.executable, "-c", rl.PARTICIPANT, "active"],
            participant,
            cwd=ROOT,
            env={**env, "EVCLOCK_CLOCK": where.join_url},
        ),
    ]
    rl.wait_all(procs)
    return rl.per_round(server, "server"), rl.per_round(participant, "participant")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--instructions", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.instructions and (shutil.which("valgrind") is None or shutil.which("gcc") is None):
        parser.error("--instructions needs valgrind and gcc, or pass --no-instructions")
    started = time.monotonic()
    token = secrets.token_urlsafe(32)
    best: dict[str, tuple[float, float, float]] = {}
    counted: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        make_certificates(folder)
        for _ in range(args.repeat):
            for name in TRANSPORTS:
                figures = lockstep(transport(name, folder, token), args.rounds)
                if figures[0] > best.get(name, (0.0,))[0]:
                    best[name] = figures
        if args.instructions:
            marks = build_marks(tmp)
            for name in TRANSPORTS:
                counted[name] = instructions(transport(name, folder, token), folder, marks)

    print(
        f"python {sys.version.split()[0]}; lockstep, 1 participant, {args.rounds} rounds; "
        f"wall figures: best of {args.repeat}, transports interleaved"
    )
    tcp_rate, tcp_server, tcp_participant = best["tcp"]
    results: dict[str, Any] = {}
    for name in TRANSPORTS:
        rate, server_us, participant_us = best[name]
        print(
            f"{name + '://':<8} {rate:>8,.0f} rounds/s ({rate / tcp_rate:.2f} x tcp); CPU per "
            f"round: server {server_us:.0f} us ({server_us / tcp_server:.2f} x tcp), "
            f"participant {participant_us:.0f} us ({participant_us / tcp_participant:.2f} x tcp)"
        )
        results[name] = {
            "rounds_per_s": rate,
            "server_cpu_us": server_us,
            "participant_cpu_us": participant_us,
        }
    if counted:
        print(
            f"\ninstructions per round under callgrind (({rl.BIG} - {rl.SMALL} rounds) / "
            f"{rl.BIG - rl.SMALL})"
        )
        print(f"  {'':<10}{'server':>10}{'participant':>13}{'sum':>10}{'x tcp':>8}")
        tcp_sum = sum(counted["tcp"])
        for name in TRANSPORTS:
            server, participant = counted[name]
            total = server + participant
            print(
                f"  {name + '://':<10}{server:>10,.0f}{participant:>13,.0f}{total:>10,.0f}"
                f"{total / tcp_sum:>7.2f}x"
            )
            results[name].update(server_instructions=server, participant_instructions=participant)
    print(f"\n(whole run: {time.monotonic() - started:.0f} s)")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
