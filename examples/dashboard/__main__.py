"""The command line: ``python examples/dashboard [--scenario kuka] [--port 8000] [--rtf 1]``.

Runs from any working directory: ``python path/to/examples/dashboard``; from the repository
root, ``python -m examples.dashboard`` works too.
"""

from __future__ import annotations

import sys
from pathlib import Path

if not __package__:
    # Run as a path (python path/to/examples/dashboard): Python put this folder first on
    # sys.path and knows no package. Import the dashboard as the package it is, from the
    # repository root two folders up, so its relative imports (and the render worker
    # process, which inherits sys.path) work from any working directory.
    sys.path[0] = str(Path(__file__).resolve().parents[2])
    __package__ = "examples.dashboard"

import argparse
import logging
import math

import uvicorn

from evclock_sims import SCENARIOS

from .app import create_app
from .config import DashboardConfig


def parse_rtf(text: str) -> float | None:
    """A real-time factor on the command line: a positive number, or ``max`` (no pacing)."""
    if text.strip().lower() in ("max", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or 'max': {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number or 'max', got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command line."""
    parser = argparse.ArgumentParser(
        prog="python examples/dashboard",
        description="Serve a live dashboard of a PyBullet scenario run on sim time by evclock.",
    )
    parser.add_argument("--scenario", default="kuka", choices=sorted(SCENARIOS))
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument(
        "--rtf", type=parse_rtf, default=1.0, help="real-time factor, or 'max' (default: 1)"
    )
    parser.add_argument("--paused", action="store_true", help="start with sim time paused")
    parser.add_argument(
        "--once",
        action="store_true",
        help="run one mission, then keep stepping the physics (default: new episode each time)",
    )
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument(
        "--loop",
        default="auto",
        choices=["auto", "asyncio", "uvloop"],
        help="uvicorn's event loop (default: uvloop when installed, else asyncio)",
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    """Parse ``argv`` and serve until interrupted (Ctrl-C)."""
    args = build_parser().parse_args(argv)
    config = DashboardConfig(
        scenario=args.scenario,
        seed=args.seed,
        rtf=args.rtf,
        paused=args.paused,
        repeat=not args.once,
    )
    logging.basicConfig(level=logging.INFO, format="%(levelname)-9s %(name)s: %(message)s")
    print(f"evclock dashboard: {args.scenario} on http://{args.host}:{args.port}/", flush=True)
    uvicorn.run(create_app(config), host=args.host, port=args.port, loop=args.loop, ws="none")


if __name__ == "__main__":
    main()
