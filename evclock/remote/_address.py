"""Clock endpoints: ``unix:///path/sim.sock`` (default), ``tcp://127.0.0.1:PORT``, or
``tls://HOST:PORT`` (the same protocol inside TLS 1.3, between machines: :mod:`._tls`).

Options ride in the query string, so one string (an argument or ``EVCLOCK_CLOCK``) says
everything a participant needs: ``unix:///tmp/sim.sock?mode=follow&name=observer``.

The default address lives in a private directory of the user (:func:`private_dir`: mode 0700,
owned by the user, never a predictable name in a shared directory), and both ends of a Unix
socket check who the other is (:func:`peer_uid`, ``SO_PEERCRED``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import ipaddress
import math
import os
import socket
import stat
import struct
import tempfile
import urllib.parse

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.remote import _tls

MODES = ("lockstep", "follow")
#: Query keys a participant's address may carry.
_PARTICIPANT_KEYS = (
    "mode",
    "name",
    "token",
    "timeout",
    "server_uid",
    "tls_ca",
    "tls_fingerprint",
)
#: Query keys that only a ``tls://`` address may carry.
_TLS_KEYS = ("tls_ca", "tls_fingerprint")
#: Schemes of a host and port.
_NETWORK_SCHEMES = ("tcp", "tls")
#: Wall seconds a participant waits for the server (to appear, to grant, to reply) by default.
DEFAULT_PEER_TIMEOUT = 60.0
#: The shortest ``timeout`` accepted: a few keepalive periods of the server.
MIN_PEER_TIMEOUT = 0.5


@dataclasses.dataclass(frozen=True)
class Address:
    """A parsed clock endpoint plus the participant options of its query string."""

    scheme: str
    path: str = ""
    host: str = ""
    port: int = 0
    mode: str = "lockstep"
    name: str | None = None
    token: str | None = None
    timeout: float = DEFAULT_PEER_TIMEOUT
    #: The user id the server of a Unix socket must run as (default: this process's user).
    server_uid: int | None = None
    #: ``tls://``: the CA file that signed the server's certificate (host name checked).
    tls_ca: str | None = None
    #: ``tls://``: the pinned SHA-256 fingerprint of the server's certificate (32 bytes).
    tls_fingerprint: bytes | None = None

    def __str__(self) -> str:
        if self.scheme == "unix":
            return f"unix://{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """Whether the endpoint is reachable from this machine only."""
        if self.scheme == "unix":
            return True
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


ONE_VERIFICATION = (
    "a tls:// server is verified one way: give tls_ca (the CA that signed its certificate) "
    "or tls_fingerprint (its certificate's fingerprint), not both"
)


def _positive_seconds(raw: str, what: str) -> float:
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise InvalidArgumentError(f"{what} must be a positive number of seconds, got {raw!r}")
    return value


def parse_address(url: object, *, participant: bool = True) -> Address:
    """Parse ``url``; ``participant`` allows the joining options in its query string."""
    if not isinstance(url, str):
        raise InvalidTypeError(
            f"a clock address is a string such as 'unix:///tmp/sim.sock', got {type(url).__name__}"
        )
    parts = urllib.parse.urlsplit(url)
    query = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=False)
    allowed = _PARTICIPANT_KEYS if participant else ("token",)
    for key, values in query.items():
        if key not in allowed:
            raise InvalidArgumentError(
                f"unknown option {key!r} in clock address {url!r}; allowed: {', '.join(allowed)}"
            )
        if len(values) != 1:
            raise InvalidArgumentError(f"option {key!r} is given twice in clock address {url!r}")
    options = {key: values[0] for key, values in query.items()}
    mode = options.get("mode", "lockstep")
    if mode not in MODES:
        raise InvalidArgumentError(
            f"mode must be 'lockstep' or 'follow' in clock address {url!r}, got {mode!r}"
        )
    name = options.get("name")
    if name is not None and not (0 < len(name.encode()) <= 255):
        raise InvalidArgumentError(f"name must be 1 to 255 bytes long, got {name!r}")
    timeout = (
        _positive_seconds(options["timeout"], "timeout")
        if "timeout" in options
        else DEFAULT_PEER_TIMEOUT
    )
    if timeout < MIN_PEER_TIMEOUT:
        raise InvalidArgumentError(
            f"timeout must be at least {MIN_PEER_TIMEOUT:g} s (the server's keepalives come "
            f"every 0.2 s), got {options['timeout']!r}"
        )
    server_uid: int | None = None
    if "server_uid" in options:
        raw_uid = options["server_uid"]
        if not raw_uid.isdigit():
            raise InvalidArgumentError(
                f"server_uid must be a numeric user id (e.g. 1000), got {raw_uid!r}"
            )
        server_uid = int(raw_uid)
    token = options.get("token")
    if token is not None and not token:
        raise InvalidArgumentError(f"token must not be empty in clock address {url!r}")
    tls_keys = [key for key in _TLS_KEYS if key in options]
    if tls_keys and parts.scheme != "tls":
        raise InvalidArgumentError(
            f"{tls_keys[0]} is an option of a tls:// clock address, not of {url!r}"
        )
    tls_ca = options.get("tls_ca")
    if tls_ca is not None and not tls_ca:
        raise InvalidArgumentError(f"tls_ca must name a CA file in clock address {url!r}")
    if len(tls_keys) == 2:
        raise InvalidArgumentError(f"{ONE_VERIFICATION}, in clock address {url!r}")
    fingerprint = options.get("tls_fingerprint")
    common = {
        "mode": mode,
        "name": name,
        "token": token,
        "timeout": timeout,
        "server_uid": server_uid,
        "tls_ca": tls_ca,
        "tls_fingerprint": None if fingerprint is None else _tls.parse_fingerprint(fingerprint),
    }
    if parts.scheme == "unix":
        if parts.netloc or not parts.path:
            raise InvalidArgumentError(
                f"a unix clock address is unix:///absolute/path.sock (three slashes), got {url!r}"
            )
        return Address("unix", path=parts.path, **common)  # type: ignore[arg-type]
    if parts.scheme in _NETWORK_SCHEMES:
        try:
            host, port = parts.hostname, parts.port
        except ValueError:
            host = port = None
        if not host or port is None:
            raise InvalidArgumentError(
                f"a {parts.scheme} clock address is {parts.scheme}://HOST:PORT (e.g. "
                f"{parts.scheme}://127.0.0.1:7411), got {url!r}"
            )
        return Address(parts.scheme, host=host, port=port, **common)  # type: ignore[arg-type]
    raise InvalidArgumentError(
        f"unsupported clock address {url!r}: use unix:///path/sim.sock, tcp://127.0.0.1:PORT "
        "or tls://HOST:PORT"
    )


def with_verification(address: Address, tls_ca: str | None, tls_fingerprint: str | None) -> Address:
    """``address`` with the CA file or the fingerprint that verifies its ``tls://`` server
    (given to the participant besides its address: it replaces the query's way)."""
    if tls_ca is None and tls_fingerprint is None:
        return address
    if address.scheme != "tls":
        raise InvalidArgumentError(
            f"tls_ca and tls_fingerprint verify a tls:// server, not {address}"
        )
    if tls_ca is not None and tls_fingerprint is not None:
        raise InvalidArgumentError(ONE_VERIFICATION)
    if tls_ca is not None:
        if not isinstance(tls_ca, str):
            raise InvalidTypeError(f"tls_ca is a file path, got {type(tls_ca).__name__}")
        return dataclasses.replace(address, tls_ca=tls_ca, tls_fingerprint=None)
    if not isinstance(tls_fingerprint, str):
        raise InvalidTypeError(
            f"tls_fingerprint is a hex string, got {type(tls_fingerprint).__name__}"
        )
    fingerprint = _tls.parse_fingerprint(tls_fingerprint)
    return dataclasses.replace(address, tls_ca=None, tls_fingerprint=fingerprint)


def listen(address: Address, *, allow_remote: bool = False) -> socket.socket:
    """A non-blocking listening socket for ``address``.

    A Unix socket file is created with owner-only permissions (0600); an existing socket
    file at the path is an error rather than silently replaced. TCP and TLS bind to a
    loopback address unless ``allow_remote``, which only TLS takes (a token is required
    on both, checked by the caller): plain TCP is for one machine.
    """
    if allow_remote and address.scheme != "tls":
        raise InvalidArgumentError(
            f"allow_remote=True is for tls:// addresses, not {address}: "
            + (
                "a unix:// socket is reached from this machine only; drop allow_remote"
                if address.scheme == "unix"
                else "plain tcp:// stays on this machine (unencrypted, and any host could "
                "pose as the server); serve across machines on tls://HOST:PORT with a "
                "certificate (tls_cert=, tls_key=) and a token"
            )
        )
    if address.scheme == "unix":
        if os.path.lexists(address.path):
            raise InvalidArgumentError(
                f"{address.path} already exists; another clock server may be serving there: "
                "stop it or remove the file, or choose another path"
            )
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o177)  # the socket file is born 0600: no window for others
        try:
            sock.bind(address.path)
        except OSError as exc:
            sock.close()
            raise InvalidArgumentError(f"cannot serve on {address}: {exc}") from None
        finally:
            os.umask(old_umask)
    else:
        if not address.is_loopback and address.scheme != "tls":
            raise InvalidArgumentError(
                f"{address} is not a loopback address, and plain tcp:// would carry the "
                "simulation's time and data unencrypted to anyone on the path and let any "
                "host pose as the server: serve across machines on tls://HOST:PORT with a "
                "certificate (tls_cert=, tls_key=) and a token"
            )
        if not address.is_loopback and not allow_remote:
            raise InvalidArgumentError(
                f"{address} is not a loopback address; a clock server binds to 127.0.0.1 "
                "unless told otherwise (allow_remote=True, on tls:// with a token)"
            )
        family = socket.AF_INET6 if ":" in address.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((address.host, address.port))
        except OSError as exc:
            sock.close()
            raise InvalidArgumentError(f"cannot serve on {address}: {exc}") from None
    sock.listen(64)
    sock.setblocking(False)
    return sock


def bound_address(sock: socket.socket, address: Address) -> Address:
    """``address`` with the port the system chose when it asked for port 0."""
    if address.scheme in _NETWORK_SCHEMES and address.port == 0:
        return dataclasses.replace(address, port=sock.getsockname()[1])
    return address


def connect(address: Address, timeout: float) -> socket.socket:
    """A blocking connection to ``address`` (``timeout`` wall seconds for this one attempt)."""
    if address.scheme == "unix":
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        target: object = address.path
    else:
        family = socket.AF_INET6 if ":" in address.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        target = (address.host, address.port)
    sock.settimeout(timeout)
    try:
        sock.connect(target)  # type: ignore[arg-type]
    except OSError:
        sock.close()
        raise
    if address.scheme in _NETWORK_SCHEMES:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _check_private(path: str) -> None:
    info = os.lstat(path)
    kind = "a directory" if stat.S_ISDIR(info.st_mode) else "not a directory"
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise InvalidArgumentError(
            f"{path} is not a private directory of this user (owner uid {info.st_uid}, mode "
            f"{stat.S_IMODE(info.st_mode):o}, {kind}): "
            "another user may have created it to intercept clock connections; remove it, or "
            "set XDG_RUNTIME_DIR, or serve on an explicit address in a directory of yours"
        )


def private_dir() -> str:
    """The user's private directory for clock sockets, created (mode 0700) if needed.

    ``$XDG_RUNTIME_DIR/evclock`` where ``XDG_RUNTIME_DIR`` is set, otherwise
    ``evclock-UID`` in the temporary directory. It is created with ``mkdir(0700)`` (which
    never follows nor replaces what exists) and then checked: a directory (not a link),
    owned by this user, with no access for anyone else.

    :returns: the directory's path.
    :raises InvalidArgumentError: the path exists but is not such a directory (another
        user created it first, or its mode was widened).
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isabs(runtime) and os.path.isdir(runtime):
        path = os.path.join(runtime, "evclock")
    else:
        path = os.path.join(tempfile.gettempdir(), f"evclock-{os.getuid()}")
    with contextlib.suppress(FileExistsError):
        os.mkdir(path, 0o700)
    _check_private(path)
    return path


_PEERCRED = struct.Struct("3i")  # struct ucred: pid, uid, gid


def peer_credentials(sock: socket.socket) -> tuple[int, int] | None:
    """``(pid, uid)`` of the process at the other end of a Unix socket (``SO_PEERCRED``),
    or None where the system does not tell (TCP, a platform without it)."""
    option = getattr(socket, "SO_PEERCRED", None)
    if sock.family != socket.AF_UNIX or option is None:
        return None
    pid, uid, _gid = _PEERCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, option, _PEERCRED.size))
    return pid, uid
