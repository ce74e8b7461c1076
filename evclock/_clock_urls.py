"""Clock URLs: ``clock="ros2:///clock"`` / ``EVCLOCK_CLOCK`` choose, at launch, an outside
clock the program follows. One factory per URL scheme; each imports its module lazily."""

from __future__ import annotations

from collections.abc import Callable

from ._errors import InvalidArgumentError, InvalidTypeError
from .sources import TimeSource


def _ros2(url: str) -> TimeSource:
    from .ros2 import source_from_url

    return source_from_url(url)


#: scheme -> factory building the time source a URL of that scheme describes.
CLOCK_SCHEMES: dict[str, Callable[[str], TimeSource]] = {"ros2": _ros2}


def source_from_clock_url(url: object) -> TimeSource:
    """The time source a clock URL describes (``ros2:///clock``)."""
    if not isinstance(url, str):
        raise InvalidTypeError(f"clock must be a URL string, got {type(url).__name__}")
    scheme, sep, _ = url.partition("://")
    factory = CLOCK_SCHEMES.get(scheme) if sep else None
    if factory is None:
        known = ", ".join(f"{s}://" for s in CLOCK_SCHEMES)
        raise InvalidArgumentError(f"unsupported clock {url!r}: known schemes are {known}")
    return factory(url)
