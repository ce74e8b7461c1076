"""The live scene view: the simulation rendered headless by PyBullet's software renderer.

A frame (``getCameraImage`` with ``ER_TINY_RENDERER``) costs tens of milliseconds of CPU and
holds Python's GIL, so it runs neither on the server's loop nor in a thread: either would
stall the simulation. A worker process keeps a *mirror* of the scenario's world - the same
scenario class built with the same seed, so the same bodies under the same ids - and for
each frame receives the pose of every body (read between two physics steps in a few
microseconds), renders it and encodes it as JPEG (Pillow).

:class:`SceneView` makes frames on demand - only while someone watches - one at a time
whoever asks, at most ``fps`` per wall second, and only when the simulation has moved since
the previous frame.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import io
import multiprocessing
import os
import time
from collections.abc import Callable

import pybullet as p

from evclock_sims import Scenario, get_scenario

try:
    from PIL import Image
except ModuleNotFoundError as exc:  # checked when the app is built, not at the first frame
    raise ModuleNotFoundError(
        "the dashboard's scene view encodes JPEG with Pillow, which is not installed: "
        "pip install 'evclock[dashboard]'"
    ) from exc


@dataclasses.dataclass(frozen=True, slots=True)
class Camera:
    """Where the view looks from: PyBullet's yaw/pitch/distance camera around a target."""

    distance: float
    """Metres from the target."""
    yaw: float
    """Degrees around the vertical axis."""
    pitch: float
    """Degrees; negative looks down."""
    target: tuple[float, float, float]
    """World point looked at, or the offset from the robot's base when ``follow``."""
    follow: bool = False
    """Keep the robot's base in view (for robots that drive away)."""


CAMERAS: dict[str, Camera] = {
    "kuka": Camera(distance=1.5, yaw=50.0, pitch=-25.0, target=(0.0, 0.0, 0.5)),
    "husky": Camera(distance=4.5, yaw=30.0, pitch=-35.0, target=(0.0, 0.0, 0.0), follow=True),
    "cartpole": Camera(distance=3.0, yaw=0.0, pitch=-10.0, target=(0.0, 0.0, 0.6)),
}
"""The camera of each bundled scenario."""


def camera_for(scenario: str) -> Camera:
    """The camera for ``scenario``; ValueError naming the known ones otherwise."""
    try:
        return CAMERAS[scenario]
    except KeyError:
        known = ", ".join(CAMERAS)
        raise ValueError(
            f"the scene view has no camera for scenario {scenario!r} (it has: {known}); "
            "add one to examples.dashboard.scene.CAMERAS"
        ) from None


@dataclasses.dataclass(frozen=True, slots=True)
class BodyPose:
    """One body's base pose and joint positions."""

    body: int
    position: tuple[float, ...]
    orientation: tuple[float, ...]
    joints: tuple[float, ...]


@dataclasses.dataclass(frozen=True, slots=True)
class WorldPose:
    """Everything the render worker needs to draw the world as it is now."""

    scenario: str
    seed: int
    episode: int
    """The world to mirror is ``get_scenario(scenario)(client, seed)``, rebuilt per episode."""
    robot: int
    bodies: tuple[BodyPose, ...]


def read_world_pose(client: int, scenario: Scenario, episode: int) -> WorldPose:
    """Read every body's pose from PyBullet ``client`` (between two physics steps)."""
    bodies = []
    for index in range(p.getNumBodies(physicsClientId=client)):
        body = p.getBodyUniqueId(index, physicsClientId=client)
        position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=client)
        count = p.getNumJoints(body, physicsClientId=client)
        states = p.getJointStates(body, range(count), physicsClientId=client) if count else []
        joints = tuple(state[0] for state in states)
        bodies.append(BodyPose(body, tuple(position), tuple(orientation), joints))
    return WorldPose(scenario.name, scenario.seed, episode, scenario.robot, tuple(bodies))


# ------------------------------------------------------------- in the render worker


@dataclasses.dataclass(slots=True)
class _Mirror:
    client: int
    world: tuple[str, int, int] | None = None
    """(scenario, seed, episode) of the world loaded, if any."""


_mirror: _Mirror | None = None
"""The render worker's PyBullet client (one per worker process)."""


def render_jpeg(pose: WorldPose, camera: Camera, width: int, height: int, quality: int) -> bytes:
    """Draw ``pose`` from ``camera`` and encode it as JPEG (runs in the render worker)."""
    global _mirror
    if _mirror is None:
        _mirror = _Mirror(p.connect(p.DIRECT))
    client = _mirror.client
    world = (pose.scenario, pose.seed, pose.episode)
    if _mirror.world != world:
        p.resetSimulation(physicsClientId=client)
        _mirror.world = None
        get_scenario(pose.scenario)(client, pose.seed)
        _mirror.world = world
    for body in pose.bodies:
        try:
            p.resetBasePositionAndOrientation(
                body.body, body.position, body.orientation, physicsClientId=client
            )
            for joint, angle in enumerate(body.joints):
                p.resetJointState(body.body, joint, angle, physicsClientId=client)
        except p.error as exc:
            raise RuntimeError(
                f"the scene view could not mirror body {body.body} of {pose.scenario!r}: it "
                "mirrors the world the scenario's constructor builds, and this body is not "
                f"part of it ({exc})"
            ) from exc
    target = camera.target
    if camera.follow:
        robot = next(body for body in pose.bodies if body.body == pose.robot)
        target = tuple(a + b for a, b in zip(robot.position, camera.target, strict=True))  # type: ignore[assignment]
    view = p.computeViewMatrixFromYawPitchRoll(
        target, camera.distance, camera.yaw, camera.pitch, 0.0, 2
    )
    projection = p.computeProjectionMatrixFOV(60.0, width / height, 0.05, 50.0)
    _, _, rgba, _, _ = p.getCameraImage(
        width,
        height,
        view,
        projection,
        renderer=p.ER_TINY_RENDERER,
        flags=p.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )
    image = Image.frombuffer("RGBA", (width, height), bytes(rgba), "raw", "RGBA", 0, 1)
    out = io.BytesIO()
    image.convert("RGB").save(out, format="JPEG", quality=quality)
    return out.getvalue()


def _lower_priority() -> None:
    """The render worker's initializer: yield the CPU to the simulation when it is busy."""
    os.nice(10)


# ---------------------------------------------------------------- in the server


@dataclasses.dataclass(frozen=True, slots=True)
class Frame:
    """One rendered view and the simulation state it shows."""

    number: int
    """1 for the first frame, then counting up."""
    jpeg: bytes
    sim_time_ns: int
    physics_steps: int
    episode: int


class SceneView:
    """Frames of the running simulation, rendered in a worker process on demand.

    ``progress`` returns ``(physics_steps, episode)`` (cheap: asked on every request);
    ``read_pose`` reads the world on the server's loop, between two physics steps, and
    ``sim_time_ns`` the time it shows - both only when a new frame is due. At most ``fps``
    frames are rendered per wall second however many clients ask, and none while the
    simulation stands still. The worker runs at a lower scheduling priority than the server
    (``nice`` +10), so on a busy machine the simulation gets the CPU first.
    """

    def __init__(
        self,
        progress: Callable[[], tuple[int, int]],
        read_pose: Callable[[], WorldPose],
        sim_time_ns: Callable[[], int],
        camera: Camera,
        *,
        fps: float,
        size: tuple[int, int],
        quality: int = 80,
    ) -> None:
        self._progress = progress
        self._read_pose = read_pose
        self._sim_time_ns = sim_time_ns
        self._camera = camera
        self._period = 1.0 / fps
        self._size = size
        self._quality = quality
        self._lock = asyncio.Lock()
        self._frame: Frame | None = None
        self._next_at = 0.0
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    @property
    def frames(self) -> int:
        """How many frames were rendered so far."""
        return 0 if self._frame is None else self._frame.number

    async def frame(self) -> Frame:
        """The latest frame: a new one if the simulation moved and the rate bound allows."""
        async with self._lock:  # one render at a time; those who waited get its frame
            last = self._frame
            steps, episode = self._progress()
            now = time.monotonic()
            still = last is not None and (steps, episode) == (last.physics_steps, last.episode)
            if last is not None and (still or now < self._next_at):
                return last
            self._next_at = now + self._period
            pose, sim_time_ns = self._read_pose(), self._sim_time_ns()
            pool = self._start_pool()
            width, height = self._size
            try:
                jpeg = await asyncio.get_running_loop().run_in_executor(
                    pool, render_jpeg, pose, self._camera, width, height, self._quality
                )
            except concurrent.futures.process.BrokenProcessPool:
                self._pool = None  # the worker died: the next frame starts a new one
                raise
            number = 1 if last is None else last.number + 1
            self._frame = Frame(number, jpeg, sim_time_ns, steps, episode)
            return self._frame

    def _start_pool(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            # spawn: a fresh interpreter (forking a process with threads is unsafe).
            context = multiprocessing.get_context("spawn")
            self._pool = concurrent.futures.ProcessPoolExecutor(
                1, mp_context=context, initializer=_lower_priority
            )
        return self._pool

    def close(self) -> None:
        """Stop the render worker (waits for a frame being rendered)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
