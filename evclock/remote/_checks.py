"""What a request from another process may carry: the checks both physics services
(PyBullet's and MuJoCo's) apply before anything reaches the engine - JSON without NaN or
infinities, and finite numbers.

A finite number is an ``int`` or a ``float`` (not a ``bool``), of magnitude below 1e300: the
engines' C code trusts its caller, and a NaN, an infinity or a huge value would reach the
simulated state.
"""

from __future__ import annotations

import json
import math
from typing import Any, Final

from evclock._errors import InvalidArgumentError, ProtocolError

#: Magnitudes at or above this are refused: far beyond any physical quantity, and a sum of
#: a few of them still fits a float.
MAX_MAGNITUDE: Final = 1e300

_NUMBER_TYPES: Final = frozenset({int, float})


def is_int(value: object) -> bool:
    """Whether ``value`` is an integer (a ``bool`` is not)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_finite_number(value: object) -> bool:
    """Whether ``value`` is a finite number below :data:`MAX_MAGNITUDE` (a ``bool`` is not)."""
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and abs(value) < MAX_MAGNITUDE  # first: an integer too large for a float fails here
        and math.isfinite(value)
    )


def all_finite_numbers(items: list[Any]) -> bool:
    """Whether every item passes :func:`is_finite_number`, in a few passes of C (a command's
    vectors are checked on every round). False sends the caller to the item-by-item check,
    which names the first bad item."""
    if not items:
        return True
    if not _NUMBER_TYPES.issuperset(map(type, items)):
        return False  # a bool, a string, a nested list, a subclass...
    try:
        # NaN or infinity anywhere makes the sum so; max() alone could skip a NaN.
        return math.isfinite(sum(map(abs, items))) and max(map(abs, items)) < MAX_MAGNITUDE
    except OverflowError:
        return False  # an integer too large for a float


def decode_request(data: bytes, what: str, shape: str = "JSON") -> Any:
    """``data`` decoded as JSON, NaN and infinities refused.

    :param data: the request's bytes.
    :param what: the request, for messages (``"a pybullet request"``).
    :param shape: what it should be, for messages (``"[name, args, kwargs] JSON"``).
    :raises InvalidArgumentError: it holds ``NaN``, ``Infinity`` or ``-Infinity``.
    :raises ProtocolError: it is not JSON.
    """

    def reject_constant(token: str) -> None:
        raise InvalidArgumentError(f"{what} holds {token}: numbers must be finite")

    try:
        return json.loads(data, parse_constant=reject_constant)
    except InvalidArgumentError:  # (a ValueError: before the clause below)
        raise
    except (ValueError, TypeError, RecursionError):
        raise ProtocolError(f"{what} is not {shape}") from None
