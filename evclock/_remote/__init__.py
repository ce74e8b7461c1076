"""Sim time across processes: a clock server in the simulation, participants that join it.

* :mod:`._address` parses ``unix:///path`` / ``tcp://host:port`` endpoints and opens sockets;
* :mod:`._protocol` is the length-prefixed binary framing and its version handshake;
* :mod:`._server` serves a :class:`~evclock.SimEventLoop`'s time (follow and lockstep);
* :mod:`._participant` is the time source of a process that joins (``clock="unix://..."``);
* :mod:`._physics` lets scenario controllers call PyBullet in the simulation process;
* :mod:`._commands` holds the ``evclock run --serve`` / ``evclock control`` logic.
"""
