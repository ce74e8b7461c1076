"""Testing: evclock's pytest plugin (run tests and their async fixtures on sim time).

Layer: the top (with ``evclock.tools``). Importing this package imports nothing of pytest;
pytest loads :mod:`evclock.testing.plugin` through the ``pytest11`` entry point.

:mod:`evclock.testing.plugin` is the module pytest loads: it holds the hooks and fixtures
(pytest finds them by module attribute) and the public names. The modules here do the work:

* ``_options``: a test's options, from the command line, ini and ``@pytest.mark.evclock``.
* ``_selection``: which tests opt in, and which plugin runs each (pytest-asyncio, anyio, evclock).
* ``_state``: what the plugin knows per pytest run (and the loops it makes) and per test.
* ``_runner``: evclock's own runner for the tests no other plugin runs, and their async fixtures.
* ``_guard``: the guard around a running async test: its loop, its sim-time limit, its reports.
* ``_budget``: the wall-time budget: a watchdog that cancels on the loop, pytest-timeout behind it.
* ``_describe``: where a test is, for reports: its tasks, a stack, a traceback.
"""
