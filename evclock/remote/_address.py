"""Clock endpoints: ``unix:///path/sim.sock`` (default) or ``tcp://127.0.0.1:PORT``.

Options ride in the query string, so one string (an argument or ``EVCLOCK_CLOCK``) says
everything a participant needs: ``unix:///tmp/sim.sock?mode=follow&name=observer``.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import socket
import urllib.parse

from evclock._errors import InvalidArgumentError, InvalidTypeError

MODES = ("lockstep", "follow")
#: Query keys a participant's address may carry.
_PARTICIPANT_KEYS = ("mode", "name", "token", "timeout")
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

    def __str__(self) -> str:
        if self.scheme == "unix":
            return f"unix://{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp://{host}:{self.port}"

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
    common = {"mode": mode, "name": name, "token": options.get("token"), "timeout": timeout}
    if parts.scheme == "unix":
        if parts.netloc or not parts.path:
            raise InvalidArgumentError(
                f"a unix clock address is unix:///absolute/path.sock (three slashes), got {url!r}"
            )
        return Address("unix", path=parts.path, **common)  # type: ignore[arg-type]
    if parts.scheme == "tcp":
        try:
            host, port = parts.hostname, parts.port
        except ValueError:
            host = port = None
        if not host or port is None:
            raise InvalidArgumentError(
                f"a tcp clock address is tcp://HOST:PORT (e.g. tcp://127.0.0.1:7411), got {url!r}"
            )
        return Address("tcp", host=host, port=port, **common)  # type: ignore[arg-type]
    raise InvalidArgumentError(
        f"unsupported clock address {url!r}: use unix:///path/sim.sock or tcp://127.0.0.1:PORT"
    )


def listen(address: Address, *, allow_remote: bool = False) -> socket.socket:
    """A non-blocking listening socket for ``address``.

    A Unix socket file is created with owner-only permissions (0600); an existing socket
    file at the path is an error rather than silently replaced. TCP binds to a loopback
    address unless ``allow_remote`` (which then requires a token, checked by the caller).
    """
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
        if not address.is_loopback and not allow_remote:
            raise InvalidArgumentError(
                f"{address} is not a loopback address; a clock server binds to 127.0.0.1 "
                "unless told otherwise (allow_remote=True with a token)"
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
    if address.scheme == "tcp" and address.port == 0:
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
    if address.scheme == "tcp":
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock
