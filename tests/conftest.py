"""Shared helpers for the test suite."""

from __future__ import annotations

import sys
from pathlib import Path

# sims/ and examples/ are plain folders at the repository root, not installed packages.
ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
