"""A participant with a token trusts nothing from a server that has not proved it knows the
token: every first answer other than a verified CHALLENGE ends the join, and nothing but the
HELLO reaches the server.

Each test runs a real impostor process listening on a loopback TCP port, answering the
HELLO as a real server would not, and recording every byte it receives; the victim is a real
participant process. Every wait is bounded (``finish``/``read_line``, ``?timeout=``, the
impostor's own socket timeouts).
"""

from __future__ import annotations

import secrets
import subprocess
from pathlib import Path

import pytest
from _remote_helpers import finish, read_line, spawn

from evclock.remote import _protocol as proto

#: A lockstep participant that would print its start time once joined.
VICTIM = """
import evclock
async def main():
    print("joined at", evclock.clock().now().nanoseconds, flush=True)
    await evclock.clock().sleep(0.001)
evclock.run(main())
"""

#: Listens on a loopback port (printed), answers each connection's HELLO with the frames in
#: argv[1] (hex), records every byte it receives from all connections to argv[2], and exits
#: once no new connection came for argv[3] seconds.
IMPOSTOR = """
import socket, sys
from evclock.remote import _protocol as proto
answer = bytes.fromhex(sys.argv[1])
listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
listener.bind(("127.0.0.1", 0))
listener.listen(8)
listener.settimeout(30)  # for the first connection
print("listening", listener.getsockname()[1], flush=True)
received = b""
while True:
    try:
        conn, _ = listener.accept()
    except TimeoutError:
        break
    listener.settimeout(float(sys.argv[3]))
    conn.settimeout(30)
    reader = proto.Reader()
    data = b""
    while not reader.feed(data):
        data = conn.recv(4096)
        received += data
        if not data:
            break
    try:
        conn.sendall(answer)
        while chunk := conn.recv(4096):
            received += chunk
    except OSError:
        pass
    conn.close()
open(sys.argv[2], "wb").write(received)
"""

TOKEN = secrets.token_urlsafe(32)


def _victim_of(
    server: subprocess.Popen[str], tmp_path: Path, timeout: float
) -> tuple[int, str, str]:
    """A participant with the token joining ``server`` (which prints the port it listens
    on): its exit code, stdout and stderr."""
    words = read_line(server).split()
    assert words[0] == "listening", words
    victim = spawn(
        tmp_path,
        VICTIM,
        EVCLOCK_CLOCK=f"tcp://127.0.0.1:{words[1]}?name=victim&token={TOKEN}&timeout={timeout}",
    )
    return finish(victim)


def _run_impostor(tmp_path: Path, answer: bytes, timeout: float = 10) -> tuple[int, str, bytes]:
    """The victim's exit code and stderr, and every byte the impostor received."""
    dump = tmp_path / "received.bin"
    impostor = spawn(tmp_path, IMPOSTOR, answer.hex(), str(dump), "2")
    code, out, err = _victim_of(impostor, tmp_path, timeout)
    assert "joined at" not in out
    impostor_code, _, impostor_err = finish(impostor)
    assert impostor_code == 0, impostor_err
    return code, err, dump.read_bytes()


def _only_hellos(received: bytes) -> list[int]:
    frames = proto.Reader().feed(received)
    assert TOKEN.encode() not in received
    return [kind for kind, _ in frames]


ANSWERS = {
    "welcome and grant": (
        proto.welcome(0, proto.MAX_FRAME, b"{}") + proto.grant(0),
        "a WELCOME",
    ),
    "grant alone": (proto.grant(0), f"a frame of kind {proto.GRANT} (b'G')"),
    "a final refusal": (
        proto.refuse("participant 'controllers' left\nforged line"),
        "a REFUSE (saying \"participant 'controllers' left\\nforged line\")",
    ),
    "time then welcome": (
        proto.time_frame(5) + proto.welcome(5, proto.MAX_FRAME, b"{}"),
        f"a frame of kind {proto.TIME} (b'T')",
    ),
    "an unknown kind": (b"\x01\x00\x00\x00Q", "a frame of kind 81 (b'Q')"),
}


@pytest.mark.parametrize("variant", list(ANSWERS))
def test_a_participant_with_a_token_refuses_a_server_that_never_proved_itself(
    tmp_path: Path, variant: str
) -> None:
    answer, what = ANSWERS[variant]
    code, err, received = _run_impostor(tmp_path, answer)
    assert code == 1
    port = err.split("tcp://127.0.0.1:")[1].split()[0]
    assert err.strip().splitlines()[-1] == (
        f"evclock.remote.JoinRefusedError: the clock server at tcp://127.0.0.1:{port} "
        f"answered the HELLO with {what} before proving it knows the token: it is an "
        "unauthenticated server (not the simulation you meant, or not an evclock clock "
        "server); nothing but the HELLO was sent to it"
    )
    assert _only_hellos(received) == [proto.HELLO]


def test_an_unproven_busy_answer_is_only_retried(tmp_path: Path) -> None:
    # Busy answers come before the server's proof: the participant sends another HELLO and
    # nothing else, and gives up at its join timeout as with a server that never answers.
    code, err, received = _run_impostor(
        tmp_path, proto.refuse("busy", proto.REFUSE_BUSY), timeout=1
    )
    assert code == 1
    assert "ClockLostError" in err.strip().splitlines()[-1]
    assert "stayed busy" in err
    kinds = _only_hellos(received)
    assert kinds == [proto.HELLO] * len(kinds)
    assert len(kinds) >= 2  # it tried again


#: A server that knows the token (argv[1]): it proves itself, welcomes the participant, then
#: closes with the reason argv[2] followed by argv[3] x's, once the participant has gone.
PROVEN = """
import socket, sys
from evclock.remote import _protocol as proto
token, then = sys.argv[1], proto.closing(sys.argv[2] + "x" * int(sys.argv[3]))
listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
listener.bind(("127.0.0.1", 0))
listener.listen(1)
listener.settimeout(30)
print("listening", listener.getsockname()[1], flush=True)
conn, _ = listener.accept()
conn.settimeout(30)
reader = proto.Reader()
def next_frame():
    while True:
        frames = reader.feed(conn.recv(4096))
        if frames:
            return frames[0]
_, hello = next_frame()
version, mode, name, nonce = proto.parse_hello(hello)
server_nonce = proto.new_nonce()
transcript = proto.transcript(version, mode, name, nonce, server_nonce)
conn.sendall(proto.challenge(server_nonce, proto.prove(token, proto.SERVER_SIDE, transcript)))
next_frame()  # the participant's proof
conn.sendall(proto.welcome(0, proto.MAX_FRAME, b"{}") + then)
while conn.recv(4096):
    pass
"""


def test_what_the_server_says_reaches_the_participant_escaped_and_bounded(
    tmp_path: Path,
) -> None:
    # Even an authenticated server's text (a CLOSING reason here) is quoted and cut before
    # it reaches the participant's error: no forged line, no 1 MB message.
    forged = "stopped\nevclock.remote.JoinRefusedError: forged"
    server = spawn(tmp_path, PROVEN, TOKEN, forged, "1000000")
    code, _, err = _victim_of(server, tmp_path, 10)
    assert code == 1
    last = err.strip().splitlines()[-1]
    assert last.startswith("evclock.ClockLostError: stopped\\nevclock.remote.JoinRefusedError")
    assert last.endswith(" more characters not shown)")
    assert len(last) < 1200
    assert "forged" not in err.replace(last, "")  # nowhere but in that one line
    finish(server)
