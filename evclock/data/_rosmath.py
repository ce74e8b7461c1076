"""ROS's own arithmetic on durations, reproduced bit for bit on integer nanoseconds.

Two conversions decide ROS's synchroniser outcomes at their boundaries:

* ``rclcpp::Duration * double`` (the ApproximateTime ``age_penalty`` weighting). Every
  rclcpp release since Humble (16.x, 28.x Jazzy, 29.x Kilted, Rolling) computes it as
  ``int64_t(long double(ns) * long double(scale))``: both operands are exact in
  ``long double``, the product is rounded once to the ``long double`` significand (round to
  nearest, ties to even) and truncated toward zero. The width of ``long double`` is the
  platform's: 64 significant bits on x86-64 Linux and macOS-x86 (the x87 extended format,
  the reference platform of ROS binaries), 113 on aarch64 Linux (IEEE quad), 53 with MSVC
  and on Apple silicon (``long double`` is ``double`` there). :func:`scale_duration_ns`
  takes that width; evclock's default is 64.
* seconds given as a float, turned into nanoseconds by ROS's Python clients: rclpy's
  ``Duration(seconds=s)`` is ``int(s * 1e9)`` (the product rounded to double, then
  truncated), genpy/rospy's ``Duration.from_sec(s)`` truncates the integer seconds and the
  fraction separately (``int(s)``, then ``int((s - int(s)) * 1e9)``). Both truncate, so
  ``1.001`` s is 1_000_999_999 ns in both (evclock's own converter rounds to the nearest:
  1_001_000_000); they disagree with each other on other values (``2.3`` s: rclpy
  2_300_000_000, rospy 2_299_999_999).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final, Literal

__all__ = [
    "LONG_DOUBLE_BITS",
    "SecondsConvention",
    "duration_scaler",
    "ros_seconds_to_ns",
    "scale_duration_ns",
]

LONG_DOUBLE_BITS: Final = (53, 64, 113)
"""The ``long double`` significand widths :func:`scale_duration_ns` models."""

SecondsConvention = Literal["ros2", "ros1"]
"""Whose float-seconds conversion: rclpy's (``"ros2"``) or genpy/rospy's (``"ros1"``)."""


def scale_duration_ns(ns: int, scale: float, significand_bits: int = 64) -> int:
    """``rclcpp::Duration(ns) * scale`` with a ``long double`` of ``significand_bits`` bits.

    The exact product ``ns * scale`` is rounded once to ``significand_bits`` significant
    bits (to nearest, ties to even) and truncated toward zero, as the C++ expression
    ``static_cast<int64_t>(static_cast<long double>(ns) * static_cast<long double>(scale))``
    does on a platform whose ``long double`` has that significand (see the module docstring).
    With 53 bits ``ns`` is first rounded to a double, as C++ does when ``long double`` is
    ``double``.

    :param ns: the duration, integer nanoseconds.
    :param scale: the finite factor (a double).
    :param significand_bits: 53, 64 or 113.
    :returns: the scaled duration, integer nanoseconds.
    """
    return duration_scaler(scale, significand_bits)(ns)


def duration_scaler(scale: float, significand_bits: int = 64) -> Callable[[int], int]:
    """:func:`scale_duration_ns` with ``scale`` fixed, precomputed (the policies' hot path).

    :param scale: the finite factor (a double).
    :param significand_bits: 53, 64 or 113.
    :returns: ``f(ns)`` equal to ``scale_duration_ns(ns, scale, significand_bits)``.
    """
    if scale == 1.0 and significand_bits > 53:
        return _identity
    numerator, denominator = float(scale).as_integer_ratio()
    shift = denominator.bit_length() - 1
    bits = significand_bits

    def scaled(ns: int) -> int:
        if bits == 53 and abs(ns).bit_length() > 53:
            ns = int(float(ns))
        product = ns * numerator
        magnitude = -product if product < 0 else product
        excess = magnitude.bit_length() - bits
        if excess > 0:
            kept, rest = divmod(magnitude, 1 << excess)
            half = 1 << (excess - 1)
            if rest > half or (rest == half and kept & 1):
                kept += 1
            magnitude = kept << excess
        truncated = magnitude >> shift
        return -truncated if product < 0 else truncated

    return scaled


def _identity(ns: int) -> int:
    return ns


def ros_seconds_to_ns(seconds: float, convention: SecondsConvention = "ros2") -> int:
    """Float seconds to nanoseconds as ROS's Python clients convert them (truncating).

    :param seconds: a finite number of seconds (ints are exact).
    :param convention: ``"ros2"`` (rclpy ``Duration(seconds=s)``) or ``"ros1"`` (genpy
        ``Duration.from_sec(s)``).
    :returns: integer nanoseconds.
    """
    if isinstance(seconds, int):
        return seconds * 1_000_000_000
    if convention == "ros2":
        return int(seconds * 1_000_000_000)
    whole = int(seconds)
    return whole * 1_000_000_000 + int((seconds - whole) * 1_000_000_000)
