"""The world outside the loop: what holds sim time and what can wake the loop.

* ``_work``: :class:`OutsideWork`, the exact accounting of executor jobs, worker threads,
  child processes, explicit holds and signal handlers, and the two answers the kernel asks
  of it (is time held, and by what; could anything outside wake a task);
* ``_threads``: what each other thread is doing right now (running, in a timed wait, parked),
  read from the interpreter.

Layer: above ``evclock.kernel``; imported by the hosts. Nothing here is public API.
"""
