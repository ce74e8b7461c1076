"""Tokens never travel on a command line, and are strong (issue 34, defects 2 and 5).

The command line reads a token from ``--token-file`` (a private file) or ``EVCLOCK_TOKEN``
and refuses ``token=`` in an address; ``evclock run --serve tcp://...`` without one writes a
fresh 256-bit token to a 0600 file of the private directory; a token below 128 bits is
refused by ``serve()`` and by participants before anything is sent.
"""

from __future__ import annotations

import os
import re
import socket
import stat
import subprocess
from pathlib import Path

import pytest
from _remote_helpers import ROOT, WAIT, read_line
from test_remote_split import CLI, wait

import evclock
from evclock.remote import WeakTokenError
from evclock.remote._participant import RemoteClockSource
from evclock.remote._token import (
    MIN_TOKEN_BITS,
    check_token,
    new_token,
    read_token_file,
    token_from,
    write_token_file,
)

STRONG = "kB2n7T0qZx4LmP9sWv3YcR"  # 22 URL-safe characters: 132 bits
WEAK_SAYS = (
    "and a token needs 128 bits (22 random URL-safe characters, 32 hex digits). The clock "
    "server proves it knows the token to anyone who connects, so a recorded proof lets a "
    "stranger test guesses offline at full speed; make one with `evclock token` (or "
    "secrets.token_urlsafe(32) in Python: 256 bits)"
)


def cli(*args: str, **env: str) -> subprocess.Popen[str]:
    environ = {k: v for k, v in os.environ.items() if k not in ("EVCLOCK_TOKEN", "EVCLOCK_CLOCK")}
    environ.update(env)
    return subprocess.Popen(
        [*CLI, *args],
        cwd=ROOT,
        env=environ,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def private_file(path: Path, text: str, mode: int = 0o600) -> Path:
    path.write_text(text)
    path.chmod(mode)
    return path


# ---------------------------------------------------------------- strength


@pytest.mark.parametrize(
    ("token", "says"),
    [
        ("1234", "4 decimal digits carry at most 13 bits"),  # fell in 0.02 s in the review
        ("hunter2-secret", "14 characters carry at most 84 bits"),
        ("z" * 21, "21 characters carry at most 126 bits"),
        ("a" * 22, "22 hex digits carry at most 88 bits"),
        ("0123456789abcdef" * 1 + "0123456789abcde", "31 hex digits carry at most 124 bits"),
        ("7" * 38, "38 decimal digits carry at most 126 bits"),
        ("", "0 characters carry at most 0 bits"),
    ],
)
def test_a_weak_token_is_refused_saying_why(token: str, says: str) -> None:
    with pytest.raises(WeakTokenError) as caught:
        check_token(token)
    assert str(caught.value) == f"the clock token is too weak: {says}, {WEAK_SAYS}"
    assert isinstance(caught.value, evclock.InvalidArgumentError)


@pytest.mark.parametrize(
    "token",
    [
        STRONG,
        "0123456789abcdef" * 2,
        "9" * 39,
        "correct horse battery staple",
        "Wq3nEo0Yh2nqzV1-8sPj5x9kHdF_aR6cLuM4tBvGe7I",  # as `evclock token` makes them
    ],
)
def test_a_token_of_128_bits_or_more_is_accepted(token: str) -> None:
    assert check_token(token) == token


def test_a_fresh_token_is_256_random_bits() -> None:
    tokens = {new_token() for _ in range(50)}
    assert len(tokens) == 50
    for token in tokens:
        assert re.fullmatch(r"[A-Za-z0-9_-]{43}", token)
    assert MIN_TOKEN_BITS == 128


def test_serve_refuses_a_weak_token_given_either_way(tmp_path: Path) -> None:
    async def serve(url: str, token: str | None) -> None:
        async with evclock.remote.serve(url, token=token):
            raise AssertionError("served with a weak token")

    for url, token in (
        ("tcp://127.0.0.1:0", "s3cret"),
        ("tcp://127.0.0.1:0?token=s3cret", None),
        (f"unix://{tmp_path / 'sim.sock'}", "hunter2-secret"),
    ):
        with pytest.raises(WeakTokenError, match=r"^the clock token is too weak: "):
            evclock.run(serve(url, token))
    assert not (tmp_path / "sim.sock").exists()  # refused before it listened


def test_a_participant_refuses_a_weak_token_before_it_connects() -> None:
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.setblocking(False)
        port = listener.getsockname()[1]
        with pytest.raises(WeakTokenError, match=r"^the clock token is too weak: 6 characters"):
            RemoteClockSource(f"tcp://127.0.0.1:{port}?token=s3cret&timeout=5")
        with pytest.raises(BlockingIOError):
            listener.accept()  # it never connected: nothing sent, no proof to test offline


# ---------------------------------------------------------------- the token file


def test_a_private_token_file_is_read(tmp_path: Path) -> None:
    path = private_file(tmp_path / "sim.token", f"{STRONG}\n")
    assert read_token_file(path) == STRONG
    assert token_from(path, {}) == STRONG
    assert token_from(None, {"EVCLOCK_TOKEN": STRONG}) == STRONG
    assert token_from(None, {}) is None


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o620, 0o602])
def test_a_token_file_open_to_others_is_refused(tmp_path: Path, mode: int) -> None:
    path = private_file(tmp_path / "sim.token", f"{STRONG}\n", mode)
    with pytest.raises(evclock.InvalidArgumentError) as caught:
        read_token_file(path)
    assert str(caught.value) == (
        f"--token-file {path} has mode {mode:04o}: the group or others may read or write it; "
        f"make it private with `chmod 600 {path}`"
    )


@pytest.mark.skipif(os.getuid() != 0, reason="giving a file to another user needs root")
def test_a_token_file_of_another_user_is_refused(tmp_path: Path) -> None:
    path = private_file(tmp_path / "sim.token", f"{STRONG}\n")
    os.chown(path, 4242, -1)
    with pytest.raises(evclock.InvalidArgumentError) as caught:
        read_token_file(path)
    assert str(caught.value) == (
        f"--token-file {path} belongs to user id 4242, not to this user ({os.getuid()}): "
        "another user could have chosen the token; use a file of your own, readable only by "
        "you (chmod 600)"
    )


@pytest.mark.parametrize("text", ["", "\n", f"{STRONG}\n{STRONG}\n", f" {STRONG}\n", "\n\n"])
def test_a_token_file_holds_the_token_alone_on_one_line(tmp_path: Path, text: str) -> None:
    path = private_file(tmp_path / "sim.token", text)
    with pytest.raises(evclock.InvalidArgumentError, match="must hold the token alone on one"):
        read_token_file(path)


def test_a_token_given_twice_or_empty_is_refused(tmp_path: Path) -> None:
    path = private_file(tmp_path / "sim.token", STRONG)
    with pytest.raises(evclock.InvalidArgumentError, match="a token is given twice, with "):
        token_from(path, {"EVCLOCK_TOKEN": STRONG})
    with pytest.raises(evclock.InvalidArgumentError, match="EVCLOCK_TOKEN is set but empty"):
        token_from(None, {"EVCLOCK_TOKEN": ""})


def test_a_written_token_file_is_new_private_and_in_the_private_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    first, second = (write_token_file(STRONG, "sim-1") for _ in range(2))
    assert first != second  # a file left behind is never reused
    for path in (first, second):
        assert path.parent == tmp_path / "evclock"
        assert re.fullmatch(r"sim-1-\w+\.token", path.name)
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert read_token_file(path) == STRONG


# ---------------------------------------------------------------- the command line

IN_ADDRESS = (
    "a token in the address (token=...) is readable by every user of the machine (a command "
    "line is public, /proc/PID/cmdline); drop it from the address and pass it with "
    "--token-file PATH (a file only you can read: chmod 600) or in the EVCLOCK_TOKEN "
    "environment variable"
)


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (["run", "kuka", "--quiet", "--serve", f"tcp://127.0.0.1:9?token={STRONG}"], "--serve"),
        (["run", "kuka", "--quiet", "--serve", f"unix:///tmp/x.sock?token={STRONG}"], "--serve"),
        (["control", "kuka", "--clock", f"tcp://127.0.0.1:9?name=c&token={STRONG}"], "--clock"),
    ],
)
def test_a_token_in_a_cli_address_is_a_usage_error(args: list[str], option: str) -> None:
    code, output = wait(cli(*args))
    assert code == 2
    lines = output.strip().splitlines()
    assert len(lines) == 1, output
    assert " ".join(output.split()) == f"error: {option}: {IN_ADDRESS}"
    assert STRONG not in output  # not echoed either


def test_a_token_file_open_to_others_is_a_usage_error(tmp_path: Path) -> None:
    path = private_file(tmp_path / "sim.token", f"{STRONG}\n", 0o644)
    code, output = wait(
        cli("control", "kuka", "--clock", "tcp://127.0.0.1:9", "--token-file", str(path))
    )
    assert code == 2
    assert " ".join(output.split()) == " ".join(
        f"error: --token-file {path} has mode 0644: the group or others may read or write it; "
        f"make it private with `chmod 600 {path}`".split()
    )


@pytest.mark.parametrize(
    "args",
    [
        ["run", "kuka", "--quiet", "--serve", "tcp://127.0.0.1:0"],
        ["control", "kuka", "--clock", "tcp://127.0.0.1:9"],
    ],
)
def test_a_weak_token_from_the_environment_is_a_usage_error(args: list[str]) -> None:
    code, output = wait(cli(*args, EVCLOCK_TOKEN="hunter2"))
    assert code == 2
    assert output.count("error:") == 1, output
    assert " ".join(output.split()).startswith(
        "error: the clock token is too weak: 7 characters carry at most 42 bits, and a token "
        "needs 128 bits"
    )
    assert "hunter2" not in output


def test_control_over_tcp_without_a_token_says_how_to_give_it() -> None:
    code, output = wait(cli("control", "kuka", "--clock", "tcp://127.0.0.1:9"))
    assert code == 2
    assert " ".join(output.split()) == (
        "error: joining the simulation at tcp://127.0.0.1:9 over tcp needs its token: pass the "
        "file `evclock run --serve` printed with --token-file PATH, or set EVCLOCK_TOKEN"
    )


def test_evclock_token_prints_a_fresh_token_and_nothing_else() -> None:
    outputs = [subprocess.run([*CLI, "token"], cwd=ROOT, capture_output=True, text=True,
                              timeout=WAIT, check=True) for _ in range(2)]  # fmt: skip
    tokens = [run.stdout for run in outputs]
    assert all(re.fullmatch(r"[A-Za-z0-9_-]{43}\n", token) for token in tokens), tokens
    assert tokens[0] != tokens[1]
    assert all(run.stderr == "" for run in outputs)


ENGINE = ["--engine", "mujoco"]  # no PyBullet needed on either end


def test_serving_tcp_without_a_token_writes_a_fresh_one_to_a_private_file() -> None:
    address = f"tcp://127.0.0.1:{free_port()}"
    server = cli("run", "cartpole", "--until", "1", *ENGINE, "--quiet", "--serve", address,
                 "--remote-controllers")  # fmt: skip
    try:
        line = read_line(server, stderr=True)
        found = re.fullmatch(
            rf"evclock: the clock token of {address} is in (/\S+\.token) \(mode 0600, removed "
            r"when this run ends\); join with --token-file \1\n",
            line,
        )
        assert found, line
        path = Path(found[1])
        info = path.stat()
        assert stat.S_IMODE(info.st_mode) == 0o600
        assert info.st_uid == os.getuid()
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700  # the private directory
        assert re.fullmatch(r"[A-Za-z0-9_-]{43}\n", path.read_text())
        joined = cli("control", "cartpole", "--until", "1", *ENGINE, "--quiet",
                     "--clock", address, "--token-file", str(path))  # fmt: skip
        code, output = wait(joined)
        assert code == 3, output  # joined, ran to --until (cut short: no verdict)
    finally:
        server_code, server_output = wait(server)
    assert server_code == 3, server_output
    assert not path.exists()  # removed when the run ended


def test_serve_and_control_read_the_token_from_the_environment() -> None:
    address = f"tcp://127.0.0.1:{free_port()}"
    token = new_token()
    server = cli("run", "cartpole", "--until", "1", *ENGINE, "--quiet", "--serve", address,
                 "--remote-controllers", EVCLOCK_TOKEN=token)  # fmt: skip
    try:
        wrong = cli("control", "cartpole", "--until", "1", *ENGINE, "--quiet", "--clock",
                    f"{address}?timeout=20", EVCLOCK_TOKEN=new_token())  # fmt: skip
        code, output = wait(wrong)
        assert code == 2, output
        assert "could not prove it knows the token" in " ".join(output.split())
        joined = cli("control", "cartpole", "--until", "1", *ENGINE, "--quiet", "--clock",
                     f"{address}?timeout=20", EVCLOCK_TOKEN=token)  # fmt: skip
        code, output = wait(joined)
        assert code == 3, output  # joined, ran to --until (cut short: no verdict)
    finally:
        server_code, server_output = wait(server)
    assert server_code == 3, server_output
    assert "token" not in server_output  # a given token is not written anywhere
