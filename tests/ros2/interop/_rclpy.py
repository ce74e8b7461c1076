"""ROS 2 nodes on rclpy, in their own processes, for the interop tests.

Each node is ``rclpy_node.py`` run by this interpreter (whose environment has ROS 2's rclpy
wheels: ``.ci/ros2_interop.sh`` builds it) on Fast DDS, ROS's default middleware, confined to
the loopback interface by ``fastdds_loopback.xml`` (Fast DDS 2, Jazzy's, reads it from
``FASTRTPS_DEFAULT_PROFILES_FILE``; Fast DDS 3, Kilted's, from
``FASTDDS_DEFAULT_PROFILES_FILE``), in the test's own domain. Every exchange with a node is
bounded in wall time.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import selectors
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType
from typing import Any

HERE = Path(__file__).resolve().parent
PROFILE = HERE / "fastdds_loopback.xml"
NODE_SCRIPT = HERE / "rclpy_node.py"
#: Wall seconds a node has to start, and to answer one command.
START_S = 60.0
ANSWER_S = 30.0
#: The distributions whose rclpy wheels the tests run against, and the Fast DDS variable that
#: names the XML profile there.
PROFILE_VARIABLES = {
    "jazzy": "FASTRTPS_DEFAULT_PROFILES_FILE",
    "kilted": "FASTDDS_DEFAULT_PROFILES_FILE",
}


def distro() -> str | None:
    """The ROS 2 distribution whose rclpy is installed (``ros-<distro>-rclpy``), or None."""
    for name in PROFILE_VARIABLES:
        try:
            importlib.metadata.version(f"ros-{name}-rclpy")
        except importlib.metadata.PackageNotFoundError:
            continue
        return name
    return None


def ros_environment(domain: int) -> dict[str, str]:
    """The environment of a node: Fast DDS (rmw_fastrtps_cpp) on loopback, domain ``domain``."""
    env = dict(os.environ)
    for variable in (
        "ROS_AUTOMATIC_DISCOVERY_RANGE",  # LOCALHOST advertises the other interfaces' addresses
        "ROS_STATIC_PEERS",
        "ROS_LOCALHOST_ONLY",
        *PROFILE_VARIABLES.values(),
    ):
        env.pop(variable, None)
    name = distro()
    assert name is not None, "no ros-<distro>-rclpy installed"
    env[PROFILE_VARIABLES[name]] = str(PROFILE)
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    return env


class RclpyNode:
    """One rclpy node in a child process (see ``rclpy_node.py`` for its commands)."""

    def __init__(self, name: str, domain: int, *, use_sim_time: bool = False) -> None:
        command = [sys.executable, str(NODE_SCRIPT), name]
        if use_sim_time:
            command.append("--use-sim-time")
        self.name = name
        self._process = subprocess.Popen(
            command,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ros_environment(domain),
        )
        self._selector = selectors.DefaultSelector()
        assert self._process.stdout is not None
        self._selector.register(self._process.stdout, selectors.EVENT_READ)
        try:
            line = self._line(START_S)
            assert line == "ready", f"rclpy node {name} said {line!r}"
        except BaseException:
            self.close()
            raise

    def _line(self, timeout: float) -> str:
        assert self._process.stdout is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._selector.select(deadline - time.monotonic()):
                line = self._process.stdout.readline()
                if not line:
                    break
                return line.strip()
        raise AssertionError(f"rclpy node {self.name}: no answer in {timeout} s{self._stderr()}")

    def _stderr(self) -> str:
        if self._process.poll() is None:
            return ""
        assert self._process.stderr is not None
        return f" (exited {self._process.returncode}: {self._process.stderr.read()[-2000:]})"

    def call(self, op: str, **arguments: Any) -> Any:
        """Send one command, return its answer."""
        assert self._process.stdin is not None
        self._process.stdin.write(json.dumps({"op": op, **arguments}) + "\n")
        self._process.stdin.flush()
        return json.loads(self._line(ANSWER_S))

    def until(self, what: str, check: Any, op: str, timeout: float = 30.0, **arguments: Any) -> Any:
        """Call ``op`` until ``check(answer)`` is true (every 20 ms, at most ``timeout`` wall
        seconds): the last answer."""
        deadline = time.monotonic() + timeout
        while True:
            answer = self.call(op, **arguments)
            if check(answer):
                return answer
            if time.monotonic() > deadline:
                raise AssertionError(f"rclpy node {self.name}: {what} not seen: {answer!r}")
            time.sleep(0.02)

    def close(self) -> None:
        """Ask the node to quit (closing its stdin), else kill it; bounded."""
        process = self._process
        if process.poll() is None:
            assert process.stdin is not None
            try:
                process.stdin.close()
                process.wait(timeout=15)
            except (OSError, subprocess.TimeoutExpired):
                process.kill()
                process.wait()
        self._selector.close()
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()

    def __enter__(self) -> RclpyNode:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
