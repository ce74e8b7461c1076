"""The interop tests share tests/ros2's helpers (``_ros2_helpers``): that folder on sys.path."""

import sys
from pathlib import Path

_ROS2_TESTS = str(Path(__file__).resolve().parent.parent)
if _ROS2_TESTS not in sys.path:
    sys.path.append(_ROS2_TESTS)
