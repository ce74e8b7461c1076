"""The README's runnable snippets run exactly as written."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"


def snippet(after_heading: str) -> str:
    text = README.read_text()
    section = text[text.index(after_heading) :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match is not None
    return match.group(1)


def run(code: str) -> str:
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_quickstart_runs_as_written() -> None:
    out = run(snippet("## Quickstart")).splitlines()
    assert out[0] == "0.000000000 s (sim)"
    assert out[1] == "4.000000000 s (sim)"
    assert out[2:4] == ["timer at 4.500000000 s (sim)", "timer at 5.000000000 s (sim)"]
    assert out[-1] == "5.000000000 s (sim)"


@pytest.mark.pybullet
def test_pybullet_snippet_runs_as_written() -> None:
    code = snippet("## PyBullet as the clock")  # at rtf=1.0, as written: about a second
    out = [line for line in run(code).splitlines() if " s: z = " in line or "landed" in line]
    assert out[0] == "0.00 s: z = 1.000 m"
    assert out[10].startswith("0.50 s: z = ")
    assert out[-1].startswith("landed at ")
    assert float(out[10].split("z = ")[1].split()[0]) < 1.0  # it fell


@pytest.mark.pybullet
def test_scenario_snippet_runs_with_the_command(tmp_path: Path) -> None:
    scenario = tmp_path / "reach.py"
    scenario.write_text(snippet("### Writing a scenario"))
    for args in (["--seed", "2"], [f"{scenario}:Reach", "--param", "gain=5"]):
        target = [] if args[0].endswith(":Reach") else [str(scenario)]
        result = subprocess.run(
            [sys.executable, "-m", "evclock", "run", *target, *args, "--quiet"],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert result.returncode == 0, result.stdout + result.stderr
        assert "reach (seed " in result.stdout
        assert "SUCCESS" in result.stdout


def test_set_up_commands_fit_a_user_and_match_ci() -> None:
    """The main-job command installs only what the main job needs; the test command installs
    the test extra itself and is what .ci/run runs on every Python (there against the wheel)."""
    text = README.read_text()
    setup = text[text.index("## Set-up") : text.index("## Quickstart")]
    main_job, tests = (block.strip() for block in re.findall(r"```bash\n(.*?)```", setup, re.S))
    assert main_job == (
        'python3 -m venv .venv && .venv/bin/pip install -e ".[pybullet]" '
        "&& .venv/bin/evclock run kuka"
    )
    assert tests == '.venv/bin/pip install -e ".[test]" && .venv/bin/python -m pytest'
    ci = (README.parent / ".ci" / "run").read_text()
    # CI runs the same pytest against the built wheel, installed with the same extra.
    assert 'pip install --quiet "$WHEEL${3:+[$3]}"' in ci
    assert 'fresh_venv .venv "$PY311" test,lint,conformance\n' in ci
    assert 'wheel_venv ".venv-$version" "${!python_var}" test\n' in ci
    assert 'installed_tests ".venv-$version"\n' in ci
    assert '"$OLDPWD/$1/bin/python" -m pytest\n' in ci
    # Conformance: test_asyncio on every supported Python, anyio's suite too on 3.11.
    assert 'conformance ".venv-$version" asyncio\n' in ci
    assert "conformance .venv all\n" in ci
    last = 'wheel_venv .venv-wheel "$PY311" test\ninstalled_tests .venv-wheel'
    assert ci.rstrip().endswith(last)
