"""What a request from another process may carry: the checks both physics services
(PyBullet's and MuJoCo's) apply before anything reaches the engine - JSON without NaN or
infinities, and finite numbers - and how anything a peer sent is shown in a log line or an
error (:func:`shown`, :func:`one_line`): quoted and cut short, so that a peer can neither
forge a line of the simulation's log (a newline, a terminal escape) nor fill it.

A finite number is an ``int`` or a ``float`` (not a ``bool``), of magnitude below 1e300: the
engines' C code trusts its caller, and a NaN, an infinity or a huge value would reach the
simulated state.
"""

from __future__ import annotations

import json
import math
import reprlib
from typing import Any, Final

from evclock._errors import InvalidArgumentError, ProtocolError

#: Magnitudes at or above this are refused: far beyond any physical quantity, and a sum of
#: a few of them still fits a float.
MAX_MAGNITUDE: Final = 1e300

_NUMBER_TYPES: Final = frozenset({int, float})

#: The most characters of a peer's string (or of the text of another value) that a message
#: shows; what is cut is counted.
SHOWN_CHARS: Final = 200
#: The most characters of a message about a peer (a refused frame's reason).
LINE_CHARS: Final = 1000

# Containers are shown by their first few items, nested a few levels: a bounded amount of
# work whatever a peer sent.
_REPR = reprlib.Repr()  # (keyword arguments only from Python 3.12)
_REPR.maxlevel = 3
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = 8
_REPR.maxstring = _REPR.maxother = SHOWN_CHARS


def shown(value: object) -> str:
    """``value`` as a message may show what a peer sent: its ``repr`` (quoted, every control
    character and newline escaped) of at most :data:`SHOWN_CHARS` characters of it, saying
    how many more were cut. A string or bytes is cut before ``repr`` (a 10 MB value costs
    no more than a short one); other values go through a bounded ``reprlib``."""
    if isinstance(value, str | bytes):
        cut = len(value) - SHOWN_CHARS
        if cut <= 0:
            return repr(value)
        unit = "characters" if isinstance(value, str) else "bytes"
        return f"{value[:SHOWN_CHARS]!r}... ({cut} more {unit} not shown)"
    if isinstance(value, int) and value.bit_length() > 4 * SHOWN_CHARS:
        return f"<an integer of {value.bit_length()} bits>"  # (repr() may refuse it)
    try:
        text = _REPR.repr(value)
    except ValueError:  # an integer too long for repr() inside a container
        return f"<a {type(value).__name__} not shown>"
    cut = len(text) - SHOWN_CHARS
    return text if cut <= 0 else f"{text[:SHOWN_CHARS]}... ({cut} more characters not shown)"


def shown_name(name: object) -> str:
    """A name a peer sent (a function's, a field's) as a message shows it: as it is if it is
    a short ASCII identifier (``qpos2``: nothing to escape), else :func:`shown`."""
    if isinstance(name, str) and len(name) <= 64 and name.isascii() and name.isidentifier():
        return name
    return shown(name)


def one_line(text: str) -> str:
    """``text`` (a message about a peer, possibly quoting what it sent) as one bounded line:
    control characters and line breaks escaped (``repr``'s escapes, without the quotes),
    at most :data:`LINE_CHARS` characters, saying how many more were cut."""
    cut = len(text) - LINE_CHARS
    head = text if cut <= 0 else text[:LINE_CHARS]
    if not head.isprintable():
        head = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in head)
    return head if cut <= 0 else f"{head}... ({cut} more characters not shown)"


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
