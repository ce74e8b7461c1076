"""The options of an evclock test: the defaults from the command line and ini, merged with the
test's ``@pytest.mark.evclock(...)``."""

from __future__ import annotations

import dataclasses
import math
from typing import Final

import pytest

from evclock._errors import PluginOptionError
from evclock.hosts._loop import DEFAULT_STALL_TIMEOUT, check_stall_timeout
from evclock.hosts._runner import _start_ns, resolve_use_sim_time
from evclock.kernel._pacing import check_rtf
from evclock.time._time import Time

#: The marker's name: ``@pytest.mark.evclock(...)``.
MARKER: Final = "evclock"
_MARKER_ARGS: Final = ("rtf", "wall_timeout", "sim_timeout", "start", "stall_timeout")
#: ``--evclock-wall-timeout``'s default (wall seconds).
DEFAULT_WALL_TIMEOUT: Final = "60"


def _parse_seconds(value: object, what: str) -> float | None:
    """A timeout: None, 0, "none" or "off" disable it; else a positive finite number."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "none", "off", "0"):
            return None
        try:
            value = float(text)
        except ValueError:
            raise PluginOptionError(
                f"{what} must be a number of seconds or 'none', got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PluginOptionError(
            f"{what} must be a number of seconds or None, got {type(value).__name__}"
        )
    if value == 0:
        return None
    if not math.isfinite(value) or value < 0:
        raise PluginOptionError(
            f"{what} must be a positive number of seconds (0 or None disables it), got {value!r}"
        )
    return float(value)


def _parse_rtf(value: object, what: str) -> float | None:
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "none"):
            return None
        try:
            value = float(text)
        except ValueError:
            raise PluginOptionError(
                f"{what} must be a positive real-time factor or 'none', got {value!r}"
            ) from None
    try:
        return check_rtf(value)
    except (TypeError, ValueError) as exc:
        raise PluginOptionError(f"{what}: {exc}") from None


@dataclasses.dataclass(frozen=True)
class Options:
    """How evclock runs one test."""

    wall: bool
    rtf: float | None
    wall_timeout: float | None
    sim_timeout: float | None
    start_ns: int = 0
    stall_timeout: float | None = DEFAULT_STALL_TIMEOUT


def config_options(config: pytest.Config) -> Options:
    """Every evclock test's defaults, from the command line and ini (UsageError if invalid)."""

    def pick(option: str, ini: str) -> object:
        value = config.getoption(option)
        return config.getini(ini) if value is None else value

    try:
        wall = bool(config.getoption("evclock_wall")) or not resolve_use_sim_time(None)
        return Options(
            wall=wall,
            rtf=_parse_rtf(pick("evclock_rtf", "evclock_rtf"), "--evclock-rtf"),
            wall_timeout=_parse_seconds(
                pick("evclock_wall_timeout", "evclock_wall_timeout"), "--evclock-wall-timeout"
            ),
            sim_timeout=_parse_seconds(
                pick("evclock_sim_timeout", "evclock_sim_timeout"), "--evclock-sim-timeout"
            ),
        )
    except ValueError as exc:
        raise pytest.UsageError(f"evclock: {exc}") from None


def marker_options(item: pytest.Item, defaults: Options) -> Options:
    """``defaults`` overridden by the test's evclock markers, the closest first
    (:class:`PluginOptionError` if one is invalid)."""
    merged: dict[str, object] = {}
    for mark in item.iter_markers(MARKER):  # closest first: a test's own marker wins
        if mark.args:
            raise PluginOptionError(
                f"@pytest.mark.evclock takes keyword arguments only ({', '.join(_MARKER_ARGS)}), "
                f"got positional {mark.args!r}"
            )
        for key, value in mark.kwargs.items():
            if key not in _MARKER_ARGS:
                raise PluginOptionError(
                    f"@pytest.mark.evclock got an unexpected argument {key!r}; "
                    f"it accepts {', '.join(_MARKER_ARGS)}"
                )
            merged.setdefault(key, value)
    options = defaults
    if "rtf" in merged:
        options = dataclasses.replace(options, rtf=_parse_rtf(merged["rtf"], "evclock(rtf=...)"))
    for key in ("wall_timeout", "sim_timeout"):
        if key in merged:
            seconds = _parse_seconds(merged[key], f"evclock({key}=...)")
            if key == "wall_timeout":
                options = dataclasses.replace(options, wall_timeout=seconds)
            else:
                options = dataclasses.replace(options, sim_timeout=seconds)
    if "stall_timeout" in merged:
        try:
            stall = check_stall_timeout(merged["stall_timeout"])
        except (TypeError, ValueError) as exc:
            raise PluginOptionError(f"evclock(stall_timeout=...): {exc}") from None
        options = dataclasses.replace(options, stall_timeout=stall)
    if "start" in merged:
        start = merged["start"]
        if not isinstance(start, int | float | Time):
            raise PluginOptionError(
                f"evclock(start=...) must be sim seconds or a sim Time, got {type(start).__name__}"
            )
        try:
            options = dataclasses.replace(options, start_ns=_start_ns(start))
        except (TypeError, ValueError) as exc:
            raise PluginOptionError(f"evclock(start=...): {exc}") from None
    return options
