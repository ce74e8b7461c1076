"""Launch-time configuration read from the environment (no dependencies: imported early)."""

from __future__ import annotations

import os

from ._errors import InvalidArgumentError

ENV_USE_SIM_TIME = "EVCLOCK_USE_SIM_TIME"
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def env_use_sim_time() -> bool | None:
    """The ``EVCLOCK_USE_SIM_TIME`` setting: True, False, or None when unset."""
    raw = os.environ.get(ENV_USE_SIM_TIME)
    if raw is None or not raw.strip():
        return None
    value = raw.strip().lower()
    if value in _TRUE:
        return True
    if value in _FALSE:
        return False
    raise InvalidArgumentError(
        f"{ENV_USE_SIM_TIME} must be one of {'/'.join(_TRUE)} or {'/'.join(_FALSE)}, got {raw!r}"
    )


# -- clock URLs (clock= / EVCLOCK_CLOCK): which outside clock a process follows -------------
ENV_CLOCK = "EVCLOCK_CLOCK"


def env_clock() -> str | None:
    """The ``EVCLOCK_CLOCK`` setting (a clock URL such as ``ros2:///clock``), or None."""
    raw = os.environ.get(ENV_CLOCK, "").strip()
    return raw or None
