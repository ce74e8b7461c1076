"""Launch-time configuration read from the environment (no dependencies: imported early)."""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

from evclock._errors import InvalidArgumentError, InvalidTypeError

if TYPE_CHECKING:
    from evclock.sources import TimeSource

ENV_USE_SIM_TIME = "EVCLOCK_USE_SIM_TIME"
"""The environment variable that decides ``use_sim_time`` when ``evclock.run()`` is not told:
``1/true/yes/on`` or ``0/false/no/off`` (unset: sim time)."""
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


ENV_CLOCK = "EVCLOCK_CLOCK"
"""The environment variable naming the clock to join when ``evclock.run()`` gets no ``clock=``:
a URL such as ``unix:///tmp/sim.sock?name=controller`` or ``ros2:///clock``."""

#: The clock-scheme registry: URL scheme -> "module:function" making the TimeSource of a URL.
#: Entries are import paths so that ``import evclock`` stays light; a package adds its own
#: scheme with :func:`register_clock_scheme` (e.g. ``ros2://``).
_CLOCK_SCHEMES: dict[str, str | Callable[[str], TimeSource]] = {
    "unix": "evclock.remote._participant:source_from_url",
    "tcp": "evclock.remote._participant:source_from_url",
    "tls": "evclock.remote._participant:source_from_url",
    "ros2": "evclock.ros2._url:source_from_url",
}


def register_clock_scheme(scheme: str, factory: str | Callable[[str], TimeSource]) -> None:
    """Make ``clock="SCHEME://..."`` (and ``EVCLOCK_CLOCK``) use ``factory(url)``.

    ``factory`` is a callable returning a new :class:`~evclock.sources.TimeSource` for the URL, or
    a ``"module:function"`` path imported on first use.

    :param scheme: the URL scheme, a lowercase identifier such as ``"ros2"``.
    :param factory: ``url -> TimeSource`` callable or ``"module:function"`` import path.
    :raises InvalidArgumentError: ``scheme`` is not a lowercase identifier.
    :raises InvalidTypeError: ``factory`` is neither callable nor a ``"module:function"`` string.

    Example::

        evclock.register_clock_scheme("mysim", "mysim.evclock:source_from_url")
        evclock.run(main(), clock="mysim://localhost")
    """
    if not isinstance(scheme, str) or not scheme.isidentifier() or scheme != scheme.lower():
        raise InvalidArgumentError(
            f"a clock scheme is a lowercase word like 'ros2', got {scheme!r}"
        )
    if not (callable(factory) or (isinstance(factory, str) and ":" in factory)):
        raise InvalidTypeError(
            "factory must be a callable url -> TimeSource or a 'module:function' string, "
            f"got {factory!r}"
        )
    _CLOCK_SCHEMES[scheme] = factory


def env_clock() -> str | None:
    """The ``EVCLOCK_CLOCK`` setting (a clock URL), or None when unset or empty."""
    raw = os.environ.get(ENV_CLOCK)
    return raw.strip() if raw and raw.strip() else None


def clock_source(url: object) -> TimeSource:
    """A new time source for the clock URL ``url``, through the scheme registry."""
    if not isinstance(url, str):
        raise InvalidTypeError(
            f"clock must be a URL string such as 'unix:///tmp/sim.sock', got {type(url).__name__}"
        )
    scheme, sep, _ = url.partition("://")
    factory = _CLOCK_SCHEMES.get(scheme) if sep else None
    if factory is None:
        known = ", ".join(f"{s}://" for s in _CLOCK_SCHEMES)
        raise InvalidArgumentError(f"unsupported clock {url!r}: known schemes are {known}")
    if isinstance(factory, str):
        module_name, _, attr = factory.partition(":")
        factory = getattr(importlib.import_module(module_name), attr)
        assert callable(factory)
    source = factory(url)
    from evclock.sources import TimeSource

    if not isinstance(source, TimeSource):
        raise InvalidTypeError(
            f"the {scheme}:// clock factory returned {type(source).__name__}, not a TimeSource"
        )
    return source
