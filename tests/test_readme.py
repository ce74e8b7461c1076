"""Every code block of README.md and of the docs (docs/**/*.md) runs as a test, as written.

How a block is tested depends on its language and on an optional annotation, an HTML comment
on the line right before its opening fence (invisible on GitHub and on the site):

* ``python``: run with ``python -c`` in a fresh directory; it must exit 0. A ``text`` block
  right after it annotated ``<!-- test: output -->`` is its exact standard output.
* ``<!-- test: pytest [ARGS] -->`` on a ``python`` block: it is a test module, run by
  ``python -m pytest ARGS`` in a fresh directory; every test must pass.
* ``<!-- test: file NAME -->`` on a ``python`` block: the file NAME, compiled here and run by
  the ``<!-- test: run NAME ... -->`` ``bash`` block of the same page that writes it out.
* ``bash``: each command is checked, not run: ``evclock`` commands parse (subcommands and
  options exist), scripts of the repository exist and take the options given, ``pip install``
  names existing extras. ``<!-- test: run [FILE ...] -->`` runs the block with bash instead,
  in a fresh directory holding the page's ``file`` blocks it names.
* ``toml``: parsed.
* ``<!-- test: skip: REASON -->``: skipped, with the reason (a diagram, a measured output, a
  command that needs ROS 2). Any other block must be annotated.
* ``pybullet`` in an annotation marks a block that needs PyBullet: skipped where it is not
  installed (tests/conftest.py), and a block that uses PyBullet must say so.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = [README, *sorted(p for p in (ROOT / "docs").rglob("*.md") if "_hooks" not in p.parts)]

FENCE = re.compile(
    r"^(?:<!-- test: (?P<note>[^\n]*?) -->\n)?```(?P<lang>\w*)\n(?P<code>.*?)^```[ \t]*$",
    re.M | re.S,
)
# (evclock_sims's MuJoCo helpers need no PyBullet.)
NEEDS_PYBULLET = re.compile(
    r"pybullet|PyBulletTimeSource|evclock (run|sweep) "
    r"|evclock_sims(?! import (?:model_path|urdf_to_mujoco|MuJoCoWorld)\b)"
)


@dataclasses.dataclass(frozen=True)
class Block:
    page: Path
    line: int
    lang: str
    code: str
    note: str  # the annotation, "" when there is none

    @property
    def words(self) -> list[str]:
        return [] if self.note.startswith("skip:") else self.note.split()

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks_of(page: Path) -> list[Block]:
    text = page.read_text(encoding="utf-8")
    return [
        Block(page, text.count("\n", 0, m.start("lang")) + 1, m["lang"], m["code"], m["note"] or "")
        for m in FENCE.finditer(text)
    ]


ALL_BLOCKS = [block for page in PAGES for block in blocks_of(page)]


def _params() -> list[object]:
    return [
        pytest.param(
            block,
            id=block.name,
            marks=[pytest.mark.pybullet] if "pybullet" in block.words else [],
        )
        for block in ALL_BLOCKS
    ]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTEST_ADDOPTS", None)
    return env


def _run(args: list[str], cwd: Path, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        args, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout, check=False
    )


def _next_block(block: Block) -> Block | None:
    page = blocks_of(block.page)
    index = page.index(block)
    return page[index + 1] if index + 1 < len(page) else None


def _previous_block(block: Block) -> Block | None:
    page = blocks_of(block.page)
    index = page.index(block)
    return page[index - 1] if index else None


# ----------------------------------------------------------------------------- checking commands


@functools.cache
def _help_of(script: str) -> str:
    result = _run([sys.executable, script, "--help"], cwd=ROOT, timeout=120)
    if result.returncode != 0 and "No module named 'pybullet'" in result.stderr:
        pytest.skip(f"{script} needs PyBullet: pip install 'evclock[pybullet]'")
    assert result.returncode == 0, f"{script} --help failed:\n{result.stderr}"
    return result.stdout


def _check_evclock(args: list[str]) -> None:
    from typer.testing import CliRunner

    from evclock.tools._cli import app

    # --help after the arguments: click still parses every subcommand and option name (an
    # unknown one is exit status 2), then prints the help instead of running the command.
    result = CliRunner().invoke(app, [*args, "--help"])
    assert result.exit_code == 0, f"evclock {shlex.join(args)}: {result.output}"


def _check_extras(spec: str) -> None:
    match = re.search(r"\[([^\]]+)\]", spec)
    if match is None:
        return
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for extra in match[1].split(","):
        assert extra.strip() in extras, f"pip install {spec}: there is no extra {extra!r}"


def _check_python(args: list[str]) -> None:
    if args[:1] == ["-m"]:
        module = args[1]
        if module == "evclock":
            _check_evclock(args[2:])
        elif module not in ("venv", "pytest", "pip"):
            assert (ROOT / module.replace(".", "/")).exists(), f"python -m {module}: no such module"
        return
    if args[:1] == ["-c"]:
        return
    script = args[0]
    path = ROOT / script
    assert path.is_file() or (path / "__main__.py").is_file(), f"python {script}: no such file"
    help_text = _help_of(script)
    for option in args[1:]:
        if option.startswith("-"):
            flag = option.split("=", 1)[0]
            assert re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", help_text), (
                f"python {script}: its --help does not offer {flag}"
            )


TOOLS = {"ruff", "mypy", "lint-imports", "mkdocs", "twine", "export", "wait", "cd", "umask"}


def check_command(tokens: list[str]) -> None:
    while tokens and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", tokens[0]):
        tokens = tokens[1:]  # VAR=value prefixes
    if not tokens:
        return
    program, args = tokens[0].rsplit("/", 1)[-1], tokens[1:]
    if program == "evclock":
        _check_evclock(args)
    elif program in ("python", "python3"):
        _check_python(args)
    elif program == "pip":
        assert args[:1] == ["install"], f"pip {shlex.join(args)}"
        for arg in args[1:]:
            if not arg.startswith("-"):
                _check_extras(arg)
    elif program == "bash":
        assert (ROOT / args[0]).is_file(), f"bash {args[0]}: no such file"
    else:
        assert program in TOOLS, (
            f"unknown program {program!r}: check it here, or annotate the block "
            "with <!-- test: skip: REASON -->"
        )


def commands_of(code: str) -> list[list[str]]:
    """The commands of a shell block: lines joined at backslashes, split at && ; & |."""
    commands: list[list[str]] = []
    for line in code.replace("\\\n", " ").splitlines():
        lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        command: list[str] = []
        for token in lexer:
            if token in ("&&", "||", ";", "&", "|"):
                commands.append(command)
                command = []
            else:
                command.append(token)
        commands.append(command)
    return [command for command in commands if command]


# ----------------------------------------------------------------------------- the blocks


@pytest.mark.parametrize("block", _params())
def test_block(block: Block, tmp_path: Path) -> None:
    if block.note.startswith("skip:"):
        pytest.skip(block.note.removeprefix("skip:").strip())
    words = block.words
    if block.lang == "python" and words[:1] == ["file"]:
        compile(block.code, words[1], "exec")
        users = [b for b in blocks_of(block.page) if b.lang == "bash" and words[1] in b.words]
        assert users, f"{block.name}: no <!-- test: run {words[1]} --> block runs this file"
    elif block.lang == "python" and words[:1] == ["pytest"]:
        (tmp_path / "test_block.py").write_text(block.code)
        args = [a for a in words[1:] if a != "pybullet"]
        pytest_args = ["-m", "pytest", "-q", "-p", "no:cacheprovider", *args, "test_block.py"]
        result = _run([sys.executable, *pytest_args], cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
    elif block.lang == "python":
        result = _run([sys.executable, "-c", block.code], cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        following = _next_block(block)
        if following is not None and following.note == "output":
            assert result.stdout.strip() == following.code.strip(), result.stdout
    elif block.note == "output":
        # An output block follows the python block it is the output of, which checks it.
        before = _previous_block(block)
        assert before is not None, block.name
        assert before.lang == "python", block.name
        assert before.words[:1] not in (["file"], ["pytest"]), block.name
        assert not before.note.startswith("skip:"), block.name
    elif block.lang == "bash" and words[:1] == ["run"]:
        for name in words[1:]:
            if name == "pybullet":
                continue
            (source,) = [b for b in blocks_of(block.page) if b.words[:2] == ["file", name]]
            (tmp_path / name).write_text(source.code)
        result = _run(["bash", "-euo", "pipefail", "-c", block.code], cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
    elif block.lang == "bash":
        for command in commands_of(block.code):
            check_command(command)
    elif block.lang == "toml":
        tomllib.loads(block.code)
    else:
        pytest.fail(
            f"{block.name}: a {block.lang or 'plain'} block must be annotated "
            "(<!-- test: output --> or <!-- test: skip: REASON -->)"
        )


def test_blocks_that_need_pybullet_are_marked() -> None:
    unmarked = [
        block.name
        for block in ALL_BLOCKS
        if block.lang in ("python", "bash")
        and not block.note.startswith("skip:")
        and (block.lang == "python" or "run" in block.words)
        and NEEDS_PYBULLET.search(block.code)
        and "pybullet" not in block.words
    ]
    assert unmarked == [], "add pybullet to their <!-- test: ... --> annotation"


def test_every_annotation_is_understood() -> None:
    known = {"output", "pytest", "file", "run", "pybullet"}
    for block in ALL_BLOCKS:
        if block.note and not block.note.startswith("skip:"):
            assert block.words[0] in known, f"{block.name}: unknown annotation {block.note!r}"


# ----------------------------------------------------------------------------- the README


def section(text: str, heading: str, end: str | None = None) -> str:
    start = text.index(heading)
    return text[start : text.index(end, start) if end else None]


def snippet(page: Path, after_heading: str) -> str:
    match = re.search(r"```python\n(.*?)```", section(page.read_text(), after_heading), re.S)
    assert match is not None
    return match.group(1)


def test_quickstart_runs_as_written() -> None:
    result = _run([sys.executable, "-c", snippet(README, "## Quickstart")], cwd=ROOT)
    assert result.returncode == 0, result.stderr
    out = result.stdout.splitlines()
    assert out[0] == "0.000000000 s (sim)"
    assert out[1:3] == ["timer at 2.500000000 s (sim)", "timer at 3.000000000 s (sim)"]
    assert out[-1] == "3.000000000 s (sim)"


@pytest.mark.pybullet
def test_pybullet_snippet_runs_as_written() -> None:
    page = ROOT / "docs" / "guides" / "physics-engines.md"
    code = snippet(page, "## PyBullet as the clock")  # at rtf=1.0, as written: about a second
    result = _run([sys.executable, "-c", code], cwd=ROOT)
    assert result.returncode == 0, result.stderr
    out = [line for line in result.stdout.splitlines() if " s: z = " in line or "landed" in line]
    assert out[0] == "0.00 s: z = 1.000 m"
    assert out[10].startswith("0.50 s: z = ")
    assert out[-1].startswith("landed at ")
    assert float(out[10].split("z = ")[1].split()[0]) < 1.0  # it fell


def test_set_up_commands_fit_a_user_and_match_ci() -> None:
    """The main-job command installs only what the main job needs; the test command installs
    the test extra itself and is what .ci/run runs on every Python (there against the wheel)."""
    text = README.read_text()
    setup = section(text, "## Set-up", "## Quickstart")
    blocks = (block.strip() for block in re.findall(r"```bash\n(.*?)```", setup, re.S))
    main_job, mujoco_job, tests = blocks
    assert main_job == (
        'python3 -m venv .venv && .venv/bin/pip install -e ".[pybullet]" '
        "&& .venv/bin/evclock run kuka"
    )
    # Python 3.12 and 3.13 (no PyBullet wheels): the same job on MuJoCo, from wheels.
    assert mujoco_job == (
        'python3 -m venv .venv && .venv/bin/pip install -e ".[mujoco]" '
        "&& .venv/bin/evclock run kuka --engine mujoco"
    )
    assert tests == '.venv/bin/pip install -e ".[test]" && .venv/bin/python -m pytest'
    ci = (README.parent / ".ci" / "run").read_text()
    # CI runs the same pytest against the built wheel, installed with the same extra (on 3.11
    # with the extras of CI's other checks too: each Python's packages are installed once).
    assert 'pip install --quiet "$WHEEL${2:+[$2]}"' in ci
    assert "phase install-3.11 wheel_install .venv-3.11 test,lint,conformance,docs\n" in ci
    for version in ("3.12", "3.13"):
        python = "$PY3" + version[2:]
        assert f'phase install-{version} wheel_venv .venv-{version} "{python}" test\n' in ci
    for version in ("3.11", "3.12", "3.13"):
        assert f"phase tests-{version} installed_tests .venv-{version}\n" in ci
    assert '"$OLDPWD/$1/bin/python" -m pytest\n' in ci
    # Conformance: test_asyncio on every supported Python, anyio's suite too on 3.11.
    assert "phase conformance-3.12 conformance .venv-3.12 asyncio\n" in ci
    assert "phase conformance-3.13 conformance .venv-3.13 asyncio\n" in ci
    assert "phase conformance-3.11 conformance .venv-3.11 all\n" in ci
    # The docs build strictly; the run ends with the phases' report, which fails it if any failed.
    assert '.venv-3.11/bin/mkdocs build --strict --site-dir "$(mktemp -d)"\n' in ci
    assert ci.rstrip().endswith("\nreport")
