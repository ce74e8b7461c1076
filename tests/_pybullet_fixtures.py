"""The ``client`` and ``client2`` fixtures: PyBullet DIRECT clients for the tests that drive
PyBullet directly, each disconnected after its test (unless the test did so itself).

A plugin of the whole suite (``pytest_plugins`` in ``conftest.py``); PyBullet is imported
only when a test asks for a client, so the suite still loads where PyBullet is missing (the
modules that use these fixtures skip themselves there).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest


def _connected() -> Iterator[int]:
    import pybullet as p

    cid = p.connect(p.DIRECT)
    yield cid
    if p.isConnected(cid):
        p.disconnect(cid)


@pytest.fixture
def client() -> Iterator[int]:
    """A DIRECT PyBullet client."""
    yield from _connected()


@pytest.fixture
def client2() -> Iterator[int]:
    """A second DIRECT PyBullet client, independent of ``client``."""
    yield from _connected()
