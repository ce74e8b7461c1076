"""Hosts of sim time: the asyncio loops and drivers that run tasks on the kernel's time.

* ``_loop``: :class:`SimEventLoop`, an asyncio loop whose ``time()`` is sim time;
* ``_driver``: :class:`SimDriver`, sim time on a loop evclock does not own (uvicorn, Jupyter);
* ``_runner``: ``evclock.run()``, loop factories, the launch-time ``use_sim_time``;
* ``_config``: launch-time configuration from the environment and clock URLs;
* ``_current``: ``evclock.clock()``, the clock of the running loop;
* ``_tasks``: where tasks wait, told for error messages.

Layer: above ``evclock.kernel``, ``evclock.sources`` and ``evclock.outside``. A host supplies
how to wait and the facts the kernel asks for; it never decides on its own whether sim time
moves. Its public names are re-exported by the top-level ``evclock`` namespace.
"""
