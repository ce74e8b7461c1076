"""Sim time across processes: a clock server in the simulation, participants that join it.

``from evclock.remote import serve, participant``. A simulation serves its time
(:func:`serve`, :class:`ClockServer`); a process joins with ``evclock.run(main(),
clock="unix://...")`` and follows it or runs in lockstep with it.

* :mod:`._address` parses ``unix:///path`` / ``tcp://host:port`` endpoints, opens sockets,
  makes the private default directory and reads a Unix peer's credentials;
* :mod:`._protocol` is the length-prefixed binary framing and its authenticated handshake;
* :mod:`._token` checks a token's strength, makes one, and reads the command line's;
* :mod:`._server` serves a :class:`~evclock.SimEventLoop`'s time (follow and lockstep),
  assembled from one part per trust boundary over :mod:`._core` (the shared state and
  sending): :mod:`._admission` (connecting, the handshake, joining), :mod:`._rounds` (holds,
  deadlines, jumps, followers' time), :mod:`._routing` (publications and subscriptions) and
  :mod:`._services` (calls); :mod:`._peer` is one connection, :mod:`._limits` what one
  participant may make the server hold;
* :mod:`._participant` is the time source of a process that joins (``clock="unix://..."``);
* :mod:`._physics` lets scenario controllers call PyBullet in the simulation process.
* :mod:`._mujoco_physics` lets them read and write MuJoCo's ``MjData`` there.


Layer: above the hosts (the server lives on a ``SimEventLoop``; the participant is a time
source); imported by ``evclock.tools`` for the command line.
"""

from evclock._errors import (
    ClockLostError,
    JoinRefusedError,
    ParticipantLostError,
    ProtocolError,
    RemoteCallError,
    RemoteClockError,
    WeakTokenError,
)
from evclock.remote._limits import Limits
from evclock.remote._participant import RemoteClockSource, participant
from evclock.remote._server import ClockServer, Message, serve

__all__ = [
    "ClockLostError",
    "ClockServer",
    "JoinRefusedError",
    "Limits",
    "Message",
    "ParticipantLostError",
    "ProtocolError",
    "RemoteCallError",
    "RemoteClockError",
    "RemoteClockSource",
    "participant",
    "serve",
    "WeakTokenError",
]

for _name in (
    "JoinRefusedError",
    "ParticipantLostError",
    "ProtocolError",
    "RemoteCallError",
    "RemoteClockError",
    "WeakTokenError",
):
    globals()[_name].__module__ = __name__
del _name
