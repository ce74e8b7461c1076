"""Services: participants' calls answered by the simulation's own code.

A service is a handler the simulation provides by name; a participant's CALL runs it at once
and the REPLY carries its result or its error. The physics services
(``_physics.PhysicsService``, ``_mujoco_physics.MjDataService``) are installed through
:meth:`~evclock.remote.ClockServer.provide` (reads) and
:meth:`~evclock.remote.ClockServer.subscribe` (commands): what a participant may ask of
the physics is decided there, request by request.
"""

from __future__ import annotations

from collections.abc import Callable

from evclock._errors import InvalidArgumentError, InvalidTypeError
from evclock.remote import _protocol as proto
from evclock.remote._checks import one_line, shown
from evclock.remote._core import ServerCore
from evclock.remote._peer import Peer


class Services(ServerCore):
    """The clock server's services and the participants' calls to them."""

    def provide(self, service: str, handler: Callable[[bytes], bytes]) -> None:
        """Answer participants' ``call(service, data)`` with ``handler(data)``, at once."""
        if not callable(handler):
            raise InvalidTypeError(f"handler must be callable, got {type(handler).__name__}")
        proto.call(0, service, b"")  # validates the name
        if service in self._services:
            raise InvalidArgumentError(f"a service named {service!r} is already provided")
        self._services[service] = handler

    def _on_call(self, peer: Peer, call_id: int, service: str, data: bytes) -> None:
        handler = self._services.get(service)
        if handler is None:
            known = ", ".join(sorted(self._services)) or "none"
            self._send(
                peer,
                proto.reply(
                    call_id, False, f"no service {shown(service)} (known: {known})".encode()
                ),
            )
            return
        try:
            result = handler(data)
        except Exception as exc:
            why = one_line(f"{type(exc).__name__}: {exc}")  # it may quote the request
            self._send(peer, proto.reply(call_id, False, why.encode()))
            return
        self._send(peer, proto.reply(call_id, True, result))
