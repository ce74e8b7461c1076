"""The recorder samples on a drift-free grid of sim time, on both engines."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest

import evclock
from evclock.sources import MuJoCoTimeSource, PyBulletTimeSource
from evclock.tools._record import Recorder

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("mcap") is None, reason="needs evclock[record] (mcap)"
)

MS = 1_000_000

PENDULUM = """
<mujoco model="pendulum">
  <option timestep="0.003"/>
  <worldbody>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/>
    </body>
  </worldbody>
</mujoco>
"""


def mujoco_source() -> MuJoCoTimeSource:
    import mujoco

    return MuJoCoTimeSource(mujoco.MjModel.from_xml_string(PENDULUM))


def pybullet_source() -> PyBulletTimeSource:
    return PyBulletTimeSource.connect(time_step=0.003)


def sample_times(path: Path, topic: str) -> list[int]:
    from mcap.reader import make_reader

    with path.open("rb") as f:
        return [m.log_time for _, c, m in make_reader(f).iter_messages() if c.topic == topic]


@pytest.mark.parametrize(
    "make_source",
    [
        pytest.param(mujoco_source, id="mujoco"),
        pytest.param(pybullet_source, id="pybullet", marks=pytest.mark.pybullet),
    ],
)
def test_samples_fall_on_the_first_step_at_or_after_each_grid_point(
    make_source: Any, tmp_path: Path
) -> None:
    """0.05 s samples on a 3 ms step: at 0, 51, 102, 150, 201, ... ms (each grid point's
    first step), not 0, 51, 102, 153 (0.05 s after the last sample: a drift of up to a step
    per sample)."""
    source = make_source()
    path = tmp_path / "run.mcap"
    recorder = Recorder(path, {})

    async def main() -> None:
        clock = evclock.clock()
        recorder.attach(source, clock, lambda: [])
        await clock.sleep(0.5)

    try:
        evclock.run(main(), source=source)
    finally:
        recorder.close()
        source.close()
    expected = [next(t for t in range(0, 600 * MS, 3 * MS) if t >= i * 50 * MS) for i in range(10)]
    assert expected[:5] == [0, 51 * MS, 102 * MS, 150 * MS, 201 * MS]
    for topic in ("/evclock/clock", "/evclock/state", "/evclock/joints"):
        assert sample_times(path, topic)[:10] == expected
