#!/usr/bin/env bash
# The interop tests against ROS 2's own client (tests/ros2/interop): rclpy nodes on Fast DDS,
# ROS's default middleware, on loopback only. Usage: .ci/ros2_interop.sh PYTHON DISTRO, e.g.
# .ci/ros2_interop.sh python3.11 jazzy. Builds a fresh venv with the checkout (editable, its
# ros2-interop extra) and the distribution's rclpy and message wheels, then runs pytest there.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "$#" -ne 2 ]; then
    echo "usage: $0 PYTHON DISTRO (DISTRO: jazzy or kilted)" >&2
    exit 2
fi
python=$1
distro=$2
case "$distro" in
    jazzy | kilted) ;;
    *) echo "$0: unknown ROS 2 distribution '$distro': jazzy or kilted" >&2; exit 2 ;;
esac

version=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
venv=".venv-ros2-$distro-$version"
rm -rf "$venv"
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install --quiet --upgrade pip
# rclpy with Fast DDS (rmw_fastrtps_cpp) and the message packages the tests use; tf2_msgs has
# no wheel (the tests read /tf through rclpy's graph and decode the samples with rosbags).
"$venv/bin/python" -m pip install --quiet -e ".[ros2-interop]" \
    "ros-$distro-rclpy[fastrtps]" "ros-$distro-rosgraph-msgs" "ros-$distro-std-msgs" \
    "ros-$distro-sensor-msgs" "ros-$distro-geometry-msgs"
echo "== ROS 2 interop: $("$venv/bin/python" --version), ros-$distro-rclpy" \
    "$("$venv/bin/python" -m pip show "ros-$distro-rclpy" 2>/dev/null | sed -n 's/^Version: //p') in $venv"
# rclpy's wheels set their library path themselves (their interpreter start-up re-executes it
# with LD_LIBRARY_PATH); the tests choose rmw_fastrtps_cpp, the domain and the loopback profile.
# No rclpy-skipped test may hide here: the run fails if any test was skipped.
"$venv/bin/python" -m pytest -n 2 -p no:randomly tests/ros2/interop -rs | tee "$venv/pytest.log"
if grep -q "skipped" "$venv/pytest.log"; then
    echo "$0: interop tests were skipped in an environment that has rclpy" >&2
    exit 1
fi
