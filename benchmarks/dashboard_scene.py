"""What the dashboard's live scene view costs the simulation: throughput with and without it.

Usage: python benchmarks/dashboard_scene.py [--scenario kuka] [--seconds 3] [--rounds 5]
[--fps 5] [--json out.json]

Each round runs the dashboard's :class:`SimService` (repeating episodes, ``rtf=None``: as
fast as possible, so any cost shows as lost throughput) on a plain asyncio loop for
``--seconds`` wall seconds, in three variants, interleaved round by round so that load from
elsewhere on the machine hits them alike:

- ``no view``: nobody watches the scene;
- ``view``: a viewer asks for frames continuously (as a page never stops refreshing); the
  scene view renders at most ``--fps`` frames per wall second in its worker process, and the
  server only reads the bodies' poses between two physics steps;
- ``render on loop``: the same frames rendered on the simulation's own loop instead (what the
  worker process avoids), for reference.

Reported per variant (medians of the rounds): physics steps per wall second, physics steps
per CPU second of the server process (what the simulation costs, immune to other load; the
render worker's own CPU is not in it), frames rendered per second, and each throughput's
ratio to ``no view`` in the same round. Target (soft, PASS or MISS, exit status 0 either
way): ``view`` keeps >= 0.95 of the ``no view`` throughput by both measures. On a machine
whose cores are all busy, the wall-time figures are noisy: quote medians of several rounds.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import statistics
import sys
import time
from pathlib import Path

# The dashboard is an example, not an installed package: import it from the repository.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from examples.dashboard import DashboardConfig, SimService
from examples.dashboard.scene import camera_for, read_world_pose, render_jpeg

VARIANTS = ("no view", "view", "render on loop")
TARGET = 0.95


async def _watch(service: SimService) -> None:
    """A viewer that never stops asking for the latest frame."""
    while True:
        await service.scene.frame()
        await asyncio.sleep(0.01)  # wall time: let the server serve others between requests


async def _render_on_loop(service: SimService, config: DashboardConfig, counter: list[int]) -> None:
    """The alternative the worker avoids: render on the simulation's loop at the same rate."""
    camera = camera_for(config.scenario)
    width, height = config.scene_size
    while True:
        episode = service.episode
        assert episode is not None
        pose = read_world_pose(service.source.client, episode.scenario, episode.number)
        render_jpeg(pose, camera, width, height, 80)
        counter[0] += 1
        await asyncio.sleep(1.0 / config.scene_fps)


async def _round(variant: str, config: DashboardConfig, seconds: float) -> tuple[float, float, int]:
    """Physics steps per wall second and per CPU second of this process over ``seconds``,
    and frames rendered meanwhile."""
    async with SimService(config) as service:
        counter = [0]
        viewer: asyncio.Task[None] | None = None
        if variant == "view":
            await service.scene.frame()  # the worker process is up before measuring
            viewer = asyncio.create_task(_watch(service))
        elif variant == "render on loop":
            viewer = asyncio.create_task(_render_on_loop(service, config, counter))
        await asyncio.sleep(0.5)  # past start-up
        first_steps, first_frames = service.physics_steps, counter[0] + service.scene.frames
        start, start_cpu = time.perf_counter(), time.process_time()
        await asyncio.sleep(seconds)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        steps = service.physics_steps - first_steps
        frames = counter[0] + service.scene.frames - first_frames
        if viewer is not None:
            viewer.cancel()
            await asyncio.gather(viewer, return_exceptions=True)
    return steps / elapsed, steps / cpu, frames


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="kuka")
    parser.add_argument("--seconds", type=float, default=3.0, help="wall seconds per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--fps", type=float, default=5.0, help="the scene view's frame bound")
    parser.add_argument("--json", type=Path, help="write the results here too")
    args = parser.parse_args()
    config = DashboardConfig(scenario=args.scenario, rtf=None, scene_fps=args.fps)

    results: dict[str, dict[str, list[float]]] = {
        variant: {"wall": [], "cpu": [], "frames": [], "wall_ratio": [], "cpu_ratio": []}
        for variant in VARIANTS
    }
    for number in range(1, args.rounds + 1):
        for variant in VARIANTS:
            gc.collect()
            wall, cpu, frames = asyncio.run(_round(variant, config, args.seconds))
            results[variant]["wall"].append(wall)
            results[variant]["cpu"].append(cpu)
            results[variant]["frames"].append(frames)
        base = results["no view"]
        for variant in VARIANTS:
            mine = results[variant]
            mine["wall_ratio"].append(mine["wall"][-1] / base["wall"][-1])
            mine["cpu_ratio"].append(mine["cpu"][-1] / base["cpu"][-1])
        line = ", ".join(f"{v} {results[v]['wall'][-1]:,.0f}" for v in VARIANTS)
        print(f"round {number} (steps per wall s): {line}", flush=True)

    print(
        f"\n{args.scenario}, rtf=max, {args.seconds:g} s x {args.rounds} rounds, "
        f"scene at most {args.fps:g} frames/s; medians"
    )
    header = ("variant", "steps/wall s", "ratio", "steps/CPU s", "ratio", "frames/s")
    print(f"{header[0]:<16}" + "".join(f"{h:>14}" for h in header[1:]))
    for variant in VARIANTS:
        median = {key: statistics.median(values) for key, values in results[variant].items()}
        print(
            f"{variant:<16}{median['wall']:>14,.0f}{median['wall_ratio']:>14.3f}"
            f"{median['cpu']:>14,.0f}{median['cpu_ratio']:>14.3f}"
            f"{median['frames'] / args.seconds:>14.1f}"
        )
    wall_ratio = statistics.median(results["view"]["wall_ratio"])
    cpu_ratio = statistics.median(results["view"]["cpu_ratio"])
    verdict = "PASS" if min(wall_ratio, cpu_ratio) >= TARGET else "MISS"
    print(
        f"{verdict}: with the scene view the simulation keeps {wall_ratio:.3f}x its wall-time "
        f"throughput and {cpu_ratio:.3f}x per CPU second (target >= {TARGET})"
    )
    if args.json is not None:
        args.json.write_text(json.dumps({"args": vars(args), "results": results}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
