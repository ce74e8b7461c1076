"""The simulation kernel: sim time, its schedule and the one rule that moves it.

* ``_core``: :class:`SimCore`, the ``(when_ns, FIFO)`` schedule and the advancement rule
  (run what is due, hold, advance by jump or by steps, pace, report a deadlock);
* ``_source``: the contract between the kernel and whatever owns "now" (a ``TimeSource``);
* ``_virtual``: the kernel's own source, pure virtual time (jumps to the next deadline);
* ``_pacing``: how much wall time an advance takes; pause, resume, step;
* ``_jumps``: time jumps (reset, restore) and their handlers;
* ``_clock``: the clock API controllers use (``SimClock``, ``WallClock``);
* ``_rate``: drift-free rate loops and timers on any clock;
* ``_precise``: precise wall-time waits for ``WallClock``.

Layer: above ``evclock.time``; imports nothing of the hosts, sources or anything higher. Hosts
(``evclock.hosts``) report facts to the kernel and ask it what to do. Its public names are
re-exported by the top-level ``evclock`` namespace and by ``evclock.sources``.
"""
