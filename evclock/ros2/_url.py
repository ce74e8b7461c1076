"""``ros2://`` clock URLs: the launch-time choice ``clock="ros2:///clock"`` /
``EVCLOCK_CLOCK=ros2:///clock``.

``ros2://[HOST:PORT]/TOPIC[?rmw=dds|zenoh&domain_id=N&connect=EP&listen=EP&startup_timeout=S&
silence_timeout=S&node_name=NAME&wire_format=W]``: ``rmw`` chooses the middleware (default:
``RMW_IMPLEMENTATION``, else DDS). On Zenoh, ``HOST:PORT`` is a shorthand for
``connect=tcp/HOST:PORT`` (default: rmw_zenoh's router on ``tcp/127.0.0.1:7447``); ``connect``
and ``listen`` may be repeated, or given empty (``listen=``) for none. A timeout of ``none``
waits forever.
"""

from __future__ import annotations

import urllib.parse
from typing import Any

from evclock._errors import InvalidArgumentError
from evclock.ros2._source import DEFAULT_SILENCE_TIMEOUT, Ros2ClockSource

SCHEME = "ros2"
_KNOWN = (
    "rmw",
    "domain_id",
    "connect",
    "listen",
    "startup_timeout",
    "silence_timeout",
    "node_name",
    "wire_format",
)


def _single(params: dict[str, list[str]], name: str, url: str) -> str | None:
    values = params.get(name)
    if values is None:
        return None
    if len(values) != 1:
        raise InvalidArgumentError(f"{name} appears {len(values)} times in {url!r}; give it once")
    return values[0]


def _endpoints(params: dict[str, list[str]], name: str) -> tuple[str, ...] | None:
    """The endpoints given for ``name`` (``name=`` alone: none at all), else None."""
    if name not in params:
        return None
    return tuple(value for value in params[name] if value)


def _seconds(text: str | None, name: str, default: float | None, url: str) -> float | None:
    if text is None:
        return default
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise InvalidArgumentError(
            f"{name} in {url!r} must be seconds or 'none', got {text!r}"
        ) from None


def source_options(url: str) -> dict[str, Any]:
    """The :class:`Ros2ClockSource` arguments a ``ros2://`` URL stands for."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != SCHEME:
        raise InvalidArgumentError(f"not a {SCHEME}:// clock URL: {url!r}")
    if not parts.path or parts.path == "/":
        raise InvalidArgumentError(
            f"{url!r} names no topic; write ros2:///clock (or ros2:///my_ns/clock)"
        )
    params = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=False)
    unknown = sorted(set(params) - set(_KNOWN))
    if unknown:
        raise InvalidArgumentError(
            f"unknown parameter(s) {', '.join(unknown)} in {url!r}; known: {', '.join(_KNOWN)}"
        )
    connect = _endpoints(params, "connect")
    if parts.netloc:
        if "connect" in params:
            raise InvalidArgumentError(f"{url!r} gives both a host and connect=; use one of them")
        connect = (f"tcp/{parts.netloc}",)
    options: dict[str, Any] = {
        "topic": parts.path,
        "connect": connect,
        "listen": _endpoints(params, "listen"),
        "startup_timeout": _seconds(
            _single(params, "startup_timeout", url), "startup_timeout", None, url
        ),
        "silence_timeout": _seconds(
            _single(params, "silence_timeout", url),
            "silence_timeout",
            DEFAULT_SILENCE_TIMEOUT,
            url,
        ),
    }
    domain = _single(params, "domain_id", url)
    if domain is not None:
        if not domain.isdigit():
            raise InvalidArgumentError(f"domain_id in {url!r} must be an integer, got {domain!r}")
        options["domain_id"] = int(domain)
    for name in ("node_name", "rmw", "wire_format"):
        value = _single(params, name, url)
        if value is not None:
            options[name] = value
    return options


def source_from_url(url: str) -> Ros2ClockSource:
    """Open a :class:`Ros2ClockSource` as a ``ros2://`` URL describes (waits for /clock).

    :param url: ``ros2://[HOST:PORT]/TOPIC`` with optional ``rmw``, ``domain_id``,
        ``node_name``, ``wire_format``, ``connect``, ``listen``, ``startup_timeout`` and
        ``silence_timeout`` query options.
    :returns: the source, once the first ``/clock`` message arrived.
    :raises InvalidArgumentError: a malformed URL, an unknown or repeated option, or an
        invalid option value.
    :raises MissingExtraError: the ``ros2`` extra is missing.
    :raises ClockLostError: no ``/clock`` message arrived within ``startup_timeout``.

    Example::

        evclock.run(main(), clock="ros2:///clock?domain_id=3")
    """
    return Ros2ClockSource(**source_options(url))
