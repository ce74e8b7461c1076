"""The remote guide's threat model names, for each statement, the test that shows it: every
name it gives is a test of the suite (a renamed or removed test fails here, not silently)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def threat_model() -> str:
    guide = (ROOT / "docs" / "guides" / "remote.md").read_text()
    start = guide.index("## Threat model\n")
    end = guide.index("\n## ", start + 1)
    return guide[start:end]


def test_every_test_the_threat_model_names_exists() -> None:
    named = re.findall(r"`(test_[a-z0-9_]+\.py)::(test_[a-z0-9_]+)`", threat_model())
    assert len(named) >= 20
    missing = []
    for file, test in named:
        path = ROOT / "tests" / "remote" / file
        source = path.read_text() if path.is_file() else ""
        if not re.search(rf"^(async )?def {test}\(", source, re.MULTILINE):
            missing.append(f"{file}::{test}")
    assert missing == []
