"""Tokens: how strong one must be, a fresh one, and where the command line reads one from.

A clock server proves it knows the token first, to anyone who connects (so that a
participant never answers an impostor); that proof is an offline oracle: whoever records it
can test guesses of the token at full speed on their own machine. Only a token too long to
guess is safe, so a token below :data:`MIN_TOKEN_BITS` is refused on both sides
(:func:`check_token`).

The command line never takes a token as an argument (another user reads
``/proc/PID/cmdline``): ``--token-file PATH`` (a file only its owner may read) or the
``EVCLOCK_TOKEN`` environment variable (:func:`token_from`). ``evclock run --serve tcp://...``
without either writes a fresh token to a 0600 file in the private directory
(:func:`write_token_file`).
"""

from __future__ import annotations

import contextlib
import math
import os
import secrets
import stat
import string
import tempfile
from pathlib import Path
from typing import Final

from evclock._errors import InvalidArgumentError, InvalidTypeError, WeakTokenError
from evclock.remote._address import private_dir

#: The least strength of a token, in bits: 22 URL-safe characters, 32 hex digits.
MIN_TOKEN_BITS: Final = 128
#: The environment variable the command line reads a token from.
ENV_TOKEN: Final = "EVCLOCK_TOKEN"
#: The largest token file read (a token is a line, not a document).
MAX_TOKEN_FILE: Final = 4096

#: The alphabets a token's strength is counted in, smallest first: a token made only of an
#: alphabet's characters carries at most log2(its size) bits per character. Any other
#: character counts as one of 64, as in URL-safe base64 (a passphrase is no stronger than that
#: per character, and usually far weaker).
_ALPHABETS: Final = (
    ("decimal digits", frozenset(string.digits), 10),
    ("hex digits", frozenset(string.hexdigits.lower()), 16),
    ("hex digits", frozenset(string.hexdigits.upper()), 16),
)
_BITS_PER_OTHER_CHAR: Final = 6.0

_HOW_TO_GET_ONE: Final = (
    "make one with `evclock token` (or secrets.token_urlsafe(32) in Python: 256 bits)"
)


def new_token() -> str:
    """A fresh random token of 256 bits (43 URL-safe characters, ``secrets.token_urlsafe``)."""
    return secrets.token_urlsafe(32)


def token_bits(token: str) -> float:
    """The most bits of strength ``token`` can carry for its length and characters."""
    used = frozenset(token)
    for _, alphabet, size in _ALPHABETS:
        if used <= alphabet:
            return len(token) * math.log2(size)
    return len(token) * _BITS_PER_OTHER_CHAR


def check_token(token: object) -> str:
    """``token`` if it is a string of at least :data:`MIN_TOKEN_BITS` bits.

    :raises InvalidTypeError: it is not a string.
    :raises WeakTokenError: it is empty or too short to be safe; the message never shows it.
    """
    if not isinstance(token, str):
        raise InvalidTypeError(f"a token is a string, got {type(token).__name__}")
    bits = token_bits(token)
    if bits < MIN_TOKEN_BITS:
        used = frozenset(token)
        kind = next(
            (name for name, alphabet, _ in _ALPHABETS if token and used <= alphabet),
            "characters",
        )
        raise WeakTokenError(
            f"the clock token is too weak: {len(token)} {kind} carry at most {bits:.0f} bits, "
            f"and a token needs {MIN_TOKEN_BITS} bits (22 random URL-safe characters, 32 hex "
            "digits). The clock server proves it knows the token to anyone who connects, so "
            "a recorded proof lets a stranger test guesses offline at full speed; "
            f"{_HOW_TO_GET_ONE}"
        )
    return token


def read_token_file(path: Path) -> str:
    """The token in the file at ``path``: one line, in a file of this user that no one else
    may read or write.

    :raises InvalidArgumentError: the file cannot be read, belongs to another user, is open
        to the group or others, or does not hold one line of UTF-8.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise InvalidArgumentError(
            f"--token-file {path}: cannot read it ({exc.strerror})"
        ) from None
    with contextlib.closing(os.fdopen(fd, "rb")) as file:
        info = os.fstat(fd)  # the file opened, not the name: no swap in between
        mode = stat.S_IMODE(info.st_mode)
        if not stat.S_ISREG(info.st_mode):
            raise InvalidArgumentError(f"--token-file {path}: not a regular file")
        if info.st_uid != os.getuid():
            raise InvalidArgumentError(
                f"--token-file {path} belongs to user id {info.st_uid}, not to this user "
                f"({os.getuid()}): another user could have chosen the token; use a file of "
                "your own, readable only by you (chmod 600)"
            )
        if mode & 0o077:
            raise InvalidArgumentError(
                f"--token-file {path} has mode {mode:04o}: the group or others may read or "
                f"write it; make it private with `chmod 600 {path}`"
            )
        raw = file.read(MAX_TOKEN_FILE + 1)
    if len(raw) > MAX_TOKEN_FILE:
        raise InvalidArgumentError(
            f"--token-file {path} is longer than {MAX_TOKEN_FILE} bytes: it should hold one "
            "line, the token"
        )
    try:
        text = raw.decode()
    except UnicodeDecodeError:
        raise InvalidArgumentError(f"--token-file {path} is not UTF-8 text") from None
    token = text.removesuffix("\n").removesuffix("\r")
    if not token or "\n" in token or "\r" in token or token != token.strip():
        raise InvalidArgumentError(
            f"--token-file {path} must hold the token alone on one line (no blank line, no "
            f"spaces around it); {_HOW_TO_GET_ONE}"
        )
    return token


def token_from(token_file: Path | None, environ: dict[str, str] | None = None) -> str | None:
    """The token the command line was given: ``--token-file`` or ``EVCLOCK_TOKEN``, or None.

    :raises InvalidArgumentError: both are given, ``EVCLOCK_TOKEN`` is set but empty, or the
        file is refused (see :func:`read_token_file`).
    """
    env = os.environ if environ is None else environ
    from_env = env.get(ENV_TOKEN)
    if token_file is not None and from_env is not None:
        raise InvalidArgumentError(
            f"a token is given twice, with --token-file and in {ENV_TOKEN}: give it one way "
            f"(unset {ENV_TOKEN}, or drop --token-file)"
        )
    if token_file is not None:
        return read_token_file(token_file)
    if from_env is not None and not from_env:
        raise InvalidArgumentError(
            f"{ENV_TOKEN} is set but empty: set it to the token, or unset it"
        )
    return from_env


def write_token_file(token: str, stem: str) -> Path:
    """``token`` in a new file ``STEM-XXXXXXXX.token`` of the private directory, created
    with mode 0600 under a name no file had (``mkstemp``: a file a killed run left behind is
    never reused nor overwritten).

    :returns: the file's path.
    """
    fd, name = tempfile.mkstemp(prefix=f"{stem}-", suffix=".token", dir=private_dir())
    with os.fdopen(fd, "w") as file:
        file.write(f"{token}\n")
    return Path(name)
