"""Fuzzing both sides of the clock server's protocol.

* An authenticated participant sends random, mutated and large frames: Hypothesis makes
  them; a real participant process sends them over a real socket while two honest lockstep
  participants and the simulation exchange data and calls. The simulation must neither
  crash nor hang, every frame of a kind a participant never sends is answered with an ERROR
  naming it, its peak memory stays bounded, and the honest participants' runs and the
  simulation's record stay bit-identical to a run without the fuzzer.
* Clients without the token drive the handshake (HELLOs, guessed PROOFs, junk, frames cut
  short) against the real server during an honest run: none is ever welcomed, the honest
  run stays bit-identical.
* An impostor server (a real process) answers a real participant's HELLO with anything
  (WELCOME, GRANT, a guessed CHALLENGE, REFUSE, junk, nothing): the participant, which has
  a token, fails with a clear error and sends it nothing after the HELLO.

Every property runs a few derandomized examples (Hypothesis' ``derandomize``): the same
cases every run, a few tens of seconds in all.
"""

from __future__ import annotations

import asyncio
import json
import socket
import subprocess
from pathlib import Path
from typing import Any

import pytest
from _remote_helpers import finish, read_line, spawn

import evclock
from evclock.remote import _protocol as proto

hypothesis = pytest.importorskip("hypothesis")
st = pytest.importorskip("hypothesis.strategies")

TOKEN = "fuzz-token-of-at-least-128-bits"

#: An honest lockstep participant: publishes its ticks, hears the other's, asks the
#: simulation to double numbers; prints everything it saw, with sim times.
HONEST = """
import json, sys, evclock
me, other, step = sys.argv[1], sys.argv[2], float(sys.argv[3])
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    seen = []
    link.subscribe("tick." + other, lambda m: seen.append(
        ["heard", m.sender, m.time.nanoseconds, m.data.decode(), clock.now().nanoseconds]))
    for i in range(15):
        await clock.sleep(step)
        link.publish("tick." + me, str(i).encode())
        seen.append(["doubled", link.call("double", str(i).encode()).decode(),
                     clock.now().nanoseconds])
    await clock.sleep(step)
    print(json.dumps(seen), flush=True)
evclock.run(main())
"""


async def _join_honest_pair(
    server: Any, tmp_path: Path, url: str, honest: list[subprocess.Popen[str]]
) -> None:
    """Start the two honest participants, one after the other (data of one time is
    delivered in join order), each joined before the next starts."""
    for me, other, step in (("a", "b", "0.001"), ("b", "a", "0.0015")):
        honest.append(
            spawn(tmp_path, HONEST, me, other, step, EVCLOCK_CLOCK=f"{url}?name={me}&token={TOKEN}")
        )
        await server.wait_for_participants(me, timeout=30)


#: Joins by hand (the handshake with the token), sends the frames in the file argv[2] (a
#: JSON list of hex strings) one by one, answering grants meanwhile, finishes its step, leaves.
FUZZER = """
import json, os, select, socket, sys, time
from evclock.remote import _protocol as proto
path, mode = sys.argv[1], int(sys.argv[3])
with open(sys.argv[2]) as listing:
    frames = json.load(listing)
sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
deadline = time.monotonic() + 30
while True:
    try:
        sock.connect(path)
        break
    except (FileNotFoundError, ConnectionRefusedError):
        assert time.monotonic() < deadline, "no server"
        time.sleep(0.02)
sock.settimeout(30)
reader = proto.Reader(proto.MAX_FRAME_LIMIT)
pending = []
def next_frame():
    while not pending:
        data = sock.recv(65536)
        if not data:
            return None
        pending.extend(reader.feed(data))
    return pending.pop(0)
nonce = proto.new_nonce()
sock.sendall(proto.hello(mode, "fuzzer", nonce))
kind, payload = next_frame()
server_nonce, _ = proto.parse_challenge(payload)
transcript = proto.transcript(proto.VERSION, mode, "fuzzer", nonce, server_nonce)
sock.sendall(proto.proof(proto.prove(os.environ["TOKEN"], proto.CLIENT_SIDE, transcript)))
kind, payload = next_frame()
assert kind == proto.WELCOME, kind
working = proto.parse_welcome(payload)[1] if mode == proto.MODE_LOCKSTEP else None
print("joined", flush=True)
errors = []
def handle(kind, payload):
    global working
    if kind == proto.ERROR:
        errors.append(proto.parse_error(payload)[0])
    elif kind == proto.GRANT:
        working = proto.parse_stamp(payload)
    elif kind == proto.JUMP:
        sock.sendall(proto.jumped(proto.parse_jump(payload)[0]))
def poll(timeout):
    while select.select([sock], [], [], timeout)[0]:
        data = sock.recv(65536)
        if not data:
            return False
        for kind, payload in reader.feed(data):
            handle(kind, payload)
        timeout = 0
    return True
for frame in frames:
    sock.sendall(bytes.fromhex(frame))
    poll(0)
    if working is not None:  # a grant came (or it joined working): finish that step
        sock.sendall(proto.done(working, proto.NO_DEADLINE))
        working = None
# Every frame was answered once a call made after them is (frames are handled in order).
sock.sendall(proto.call(4242, "double", b"1"))
while True:
    item = next_frame()
    assert item is not None, "the server closed"
    kind, payload = item
    handle(kind, payload)
    if kind == proto.REPLY and proto.parse_reply(payload)[0] == 4242:
        break
    if working is not None:
        sock.sendall(proto.done(working, proto.NO_DEADLINE))
        working = None
sock.sendall(proto.bye())
print(json.dumps(errors), flush=True)
"""

#: The kinds a participant may send; any other kind must be answered with an ERROR.
PARTICIPANT_KINDS = frozenset(
    {proto.DONE, proto.PUBLISH, proto.SUBSCRIBE, proto.CALL, proto.BYE, proto.JUMPED}
)


def _frame(kind: int, payload: bytes) -> bytes:
    return proto._frame(kind, payload)


names = st.text(alphabet="abcdefghij.", min_size=1, max_size=12).filter(
    lambda name: not name.startswith("tick")
)
times = st.sampled_from([0, 1, 999_999, 1_000_000, 2**62, -1, -(2**63)])
valid_frames = st.one_of(
    st.builds(proto.done, times, times),
    st.builds(proto.publish, times, names, st.binary(max_size=32)),
    st.builds(proto.subscribe, names),
    st.builds(
        proto.call,
        st.integers(0, 2**32 - 1),
        st.sampled_from(["double", "nope", "tick.a"]),
        st.binary(max_size=16),
    ),
    st.builds(proto.jumped, st.integers(0, 2**32 - 1)),
    st.builds(proto.hello, st.integers(0, 255), st.just("x"), st.binary(min_size=32, max_size=32)),
    st.builds(proto.proof, st.binary(max_size=32)),
)


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    """A valid frame with bytes of its kind and payload changed (its length kept; never
    made a BYE, which would end the fuzzer's turn)."""
    frame = bytearray(draw(valid_frames))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(4, len(frame) - 1))
        frame[at] = draw(st.integers(0, 255))
    if frame[4] == proto.BYE:
        frame[4] = proto.DONE
    return bytes(frame)


random_frames = st.builds(
    _frame, st.integers(0, 255).filter(lambda k: k != proto.BYE), st.binary(max_size=40)
)
#: Frames of up to 256 KiB: what the simulation holds of them while it handles them.
big_frames = st.one_of(
    st.builds(lambda n, t: proto.publish(t, "big", b"\xa5" * n), st.integers(0, 1 << 18), times),
    st.builds(lambda n: proto.call(9, "double", b"7" * n), st.integers(0, 1 << 18)),
)
frames = st.lists(
    st.one_of(valid_frames, mutated(), random_frames, big_frames), min_size=1, max_size=25
)
#: What the simulation's process may grow by (peak resident memory) while a fuzzer sends
#: at most 25 frames of at most 256 KiB (6.25 MiB): a generous bound, far below a leak's.
MAX_GROWTH = 48 * 1024 * 1024


def _reset_peak_memory() -> None:
    """Start this process's peak resident memory (VmHWM) again from its current size."""
    Path("/proc/self/clear_refs").write_text("5")


def _memory() -> dict[str, int]:
    """This process's resident memory now and at its peak (bytes)."""
    fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines())
    return {key: int(fields[key].split()[0]) * 1024 for key in ("VmRSS", "VmHWM")}


def _write_frames(folder: Path, frames: list[bytes]) -> str:
    listing = folder / f"frames-{len(list(folder.glob('frames-*')))}.json"
    listing.write_text(json.dumps([frame.hex() for frame in frames]))
    return str(listing)


def _kind(frame: bytes) -> int:
    return frame[4]


def run_simulation(tmp_path: Path, fuzz: list[bytes] | None, mode: int) -> list[object]:
    """The simulation with the honest participants (and the fuzzer): everything it saw."""
    url = f"unix://{tmp_path / 'sim.sock'}"
    honest: list[Any] = []
    record: list[object] = []
    fuzzer = None

    async def main() -> None:
        nonlocal fuzzer
        clock = evclock.clock()
        async with evclock.remote.serve(url, token=TOKEN, step_timeout=20) as server:
            server.provide("double", lambda data: str(2 * int(data)).encode())
            for topic in ("tick.a", "tick.b"):
                server.subscribe(
                    topic,
                    lambda m: record.append([m.sender, m.topic, m.time.nanoseconds, m.data.hex()]),
                )
            if fuzz is not None:
                _reset_peak_memory()
                memory.append(_memory())
                fuzzer = spawn(
                    tmp_path,
                    FUZZER,
                    url.removeprefix("unix://"),
                    _write_frames(tmp_path, fuzz),
                    str(mode),
                    TOKEN=TOKEN,
                )
            await _join_honest_pair(server, tmp_path, url, honest)
            await server.wait_until_left("a", "b")
            record.append(["end", clock.now().nanoseconds])
            if fuzz is not None:
                memory.append(_memory())

    memory: list[dict[str, int]] = []
    evclock.run(main())
    if fuzz is not None:  # the server's memory, while the fuzzer was at it
        before, after = memory
        assert after["VmHWM"] - before["VmRSS"] < MAX_GROWTH, (before, after)
    outputs: list[object] = []
    for proc in honest:
        code, out, err = finish(proc)
        assert code == 0, err
        outputs.append(json.loads(out))
    if fuzzer is not None:
        code, out, err = finish(fuzzer)
        assert code == 0, err
        joined, errors = out.splitlines()
        assert joined == "joined"
        unknown = sorted(_kind(f) for f in fuzz or [] if _kind(f) not in PARTICIPANT_KINDS)
        about = json.loads(errors)
        assert [k for k in sorted(about) if k not in PARTICIPANT_KINDS] == unknown
    return [record, outputs]


@pytest.fixture(scope="module")
def baseline(tmp_path_factory: pytest.TempPathFactory) -> list[object]:
    return run_simulation(tmp_path_factory.mktemp("baseline"), None, proto.MODE_LOCKSTEP)


@hypothesis.settings(
    max_examples=10,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(hypothesis.HealthCheck),
)
@hypothesis.given(fuzz=frames, mode=st.sampled_from([proto.MODE_LOCKSTEP, proto.MODE_FOLLOW]))
def test_a_fuzzing_participant_never_changes_an_honest_run(
    tmp_path_factory: pytest.TempPathFactory,
    baseline: list[object],
    fuzz: list[bytes],
    mode: int,
) -> None:
    assert run_simulation(tmp_path_factory.mktemp("fuzz"), fuzz, mode) == baseline


def test_the_fuzzer_is_heard(tmp_path: Path) -> None:
    # The harness itself: a frame of an unknown kind is answered, a valid call succeeds.
    url = f"unix://{tmp_path / 'sim.sock'}"
    frames = [_frame(ord("Q"), b"junk"), proto.call(7, "double", b"21")]

    async def main() -> str:
        async with evclock.remote.serve(url, token=TOKEN) as server:
            server.provide("double", lambda data: str(2 * int(data)).encode())
            proc = spawn(
                tmp_path,
                FUZZER,
                url.removeprefix("unix://"),
                _write_frames(tmp_path, frames),
                str(proto.MODE_FOLLOW),
                TOKEN=TOKEN,
            )
            await server.wait_for_participants("fuzzer")
            await server.wait_until_left()
        code, out, err = finish(proc)
        assert code == 0, err
        return out

    assert evclock.run(main()).splitlines() == ["joined", f"[{ord('Q')}]"]


# ------------------------------------------------------------------ the handshake, client side

#: Opens one connection per attempt in argv[2] (a JSON list of hex byte strings: what an
#: unauthenticated client sends first), reads what the server answers (briefly: a stalled
#: handshake is the server's to end) and prints, per attempt, the kinds of frames it got.
HANDSHAKER = """
import json, socket, sys, time
from evclock.remote import _protocol as proto
path, attempts = sys.argv[1], json.loads(sys.argv[2])
answers = []
for attempt in attempts:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    deadline = time.monotonic() + 30
    while True:
        try:
            sock.connect(path)
            break
        except (FileNotFoundError, ConnectionRefusedError):
            assert time.monotonic() < deadline, "no server"
            time.sleep(0.02)
    try:
        sock.sendall(bytes.fromhex(attempt))
    except OSError:
        pass  # refused at once (its answer is still readable)
    sock.settimeout(0.3)
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except (TimeoutError, OSError):
        pass
    sock.close()
    kinds, pos = [], 0
    while len(data) - pos >= 5:
        length = int.from_bytes(data[pos:pos + 4], "little")
        kinds.append(data[pos + 4])
        pos += 4 + length
    answers.append(kinds)
print(json.dumps(answers), flush=True)
"""

nonces = st.binary(min_size=32, max_size=32)
hellos = st.builds(
    proto.hello, st.sampled_from([proto.MODE_LOCKSTEP, proto.MODE_FOLLOW, 7]), names, nonces
)
first_frames = st.one_of(
    hellos,
    st.builds(proto.hello, st.just(proto.MODE_LOCKSTEP), names, nonces, st.integers(0, 65535)),
    st.builds(proto.proof, st.binary(max_size=40)),
    valid_frames,
    mutated(),
    random_frames,
)
#: What a client without the token sends first: frames (a HELLO and a guessed PROOF among
#: them), raw bytes, a frame cut short.
attempts = st.one_of(
    st.lists(first_frames, min_size=1, max_size=4).map(b"".join),
    st.tuples(hellos, st.builds(proto.proof, st.binary(min_size=32, max_size=32))).map(b"".join),
    st.binary(min_size=1, max_size=64),
    first_frames.flatmap(lambda f: st.integers(1, len(f) - 1).map(lambda n: f[:n])),
)


def run_with_handshakes(tmp_path: Path, tries: list[bytes]) -> tuple[list[object], Any]:
    """The simulation with the honest participants while unauthenticated clients try
    ``tries``: what the simulation and the honest participants saw, and the answers."""
    url = f"unix://{tmp_path / 'sim.sock'}"
    honest: list[Any] = []
    record: list[object] = []
    joined: list[tuple[str, ...]] = []
    client = spawn(
        tmp_path, HANDSHAKER, url.removeprefix("unix://"), json.dumps([t.hex() for t in tries])
    )
    tried: list[tuple[int, str, str]] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        clock = evclock.clock()
        async with evclock.remote.serve(url, token=TOKEN, step_timeout=20) as server:
            server.provide("double", lambda data: str(2 * int(data)).encode())
            for topic in ("tick.a", "tick.b"):
                server.subscribe(
                    topic,
                    lambda m: record.append([m.sender, m.topic, m.time.nanoseconds, m.data.hex()]),
                )
            await _join_honest_pair(server, tmp_path, url, honest)
            await server.wait_until_left("a", "b")
            record.append(["end", clock.now().nanoseconds])
            # Served until the client has made every attempt.
            tried.append(await loop.run_in_executor(None, finish, client))
            joined.append(server.participants)

    evclock.run(main())
    outputs = []
    for proc in honest:
        code, out, err = finish(proc)
        assert code == 0, err
        outputs.append(json.loads(out))
    ((code, out, err),) = tried
    assert code == 0, err
    assert joined == [()]  # nobody but the honest two ever joined
    return [record, outputs], json.loads(out)


@hypothesis.settings(
    max_examples=3,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(hypothesis.HealthCheck),
)
@hypothesis.given(tries=st.lists(attempts, min_size=8, max_size=8))
def test_handshakes_without_the_token_never_join_nor_change_an_honest_run(
    tmp_path_factory: pytest.TempPathFactory, baseline: list[object], tries: list[bytes]
) -> None:
    seen, answers = run_with_handshakes(tmp_path_factory.mktemp("handshake"), tries)
    assert seen == baseline
    assert len(answers) == len(tries)
    for attempt, kinds in zip(tries, answers, strict=True):
        # A CHALLENGE (to a HELLO), then at most a REFUSE: never a WELCOME, nothing else.
        assert proto.WELCOME not in kinds, attempt.hex()
        assert set(kinds) <= {proto.CHALLENGE, proto.REFUSE}, (attempt.hex(), kinds)


# ------------------------------------------------------------------ an impostor server

#: A fake server (a real process): it reads each connection's HELLO and answers it with the
#: bytes argv[2] gives for the name in that HELLO (p0, p1, ...), then records every byte the
#: participant sends after its HELLO; a HELLO named "stop" makes it print those counts per
#: name and end.
IMPOSTOR = """
import json, socket, sys, threading
from evclock.remote import _protocol as proto
path, answers = sys.argv[1], [bytes.fromhex(a) for a in json.loads(sys.argv[2])]
after_hello = {}
lock = threading.Lock()
def serve(conn):
    reader = proto.Reader(proto.MAX_FRAME_LIMIT)
    frames = []
    conn.settimeout(30)
    try:
        while not frames:
            chunk = conn.recv(65536)
            if not chunk:
                return
            frames = reader.feed(chunk)
        kind, payload = frames[0]
        name = proto.parse_hello(payload)[2]
        if name == "stop":
            with lock:
                print(json.dumps(after_hello), flush=True)
            done.set()
            return
        rest = sum(5 + len(p) for _, p in frames[1:]) + len(reader.pending)
        answer = answers[int(name[1:])]
        if answer:
            conn.sendall(answer)
        while chunk := conn.recv(65536):
            rest += len(chunk)
    except OSError:
        pass
    finally:
        conn.close()
    with lock:
        after_hello[name] = after_hello.get(name, 0) + rest
listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
listener.bind(path)
listener.listen(16)
print("ready", flush=True)
def accept():
    while True:
        try:
            conn, _ = listener.accept()
        except OSError:
            return
        threading.Thread(target=serve, args=(conn,), daemon=True).start()
done = threading.Event()
threading.Thread(target=accept, daemon=True).start()
done.wait(120)
"""

server_frames = st.one_of(
    st.builds(proto.welcome, times, st.integers(0, 2**32 - 1), st.binary(max_size=16)),
    st.builds(proto.grant, times),
    st.builds(proto.time_frame, times),
    st.builds(proto.challenge, nonces, st.binary(max_size=40)),
    st.builds(
        proto.refuse,
        st.text(max_size=20),
        st.sampled_from([proto.REFUSE_FINAL, proto.REFUSE_BUSY, 9]),
    ),
    st.builds(proto.error, st.integers(0, 255), st.text(max_size=20)),
    st.builds(proto.closing, st.text(max_size=20)),
    st.builds(proto.deliver, times, names, names, st.binary(max_size=16)),
    st.builds(proto.reply, st.integers(0, 2**32 - 1), st.booleans(), st.binary(max_size=8)),
    st.builds(proto.jump, st.integers(0, 2**32 - 1), times, times),
    random_frames,
)
#: What an impostor answers a HELLO with: frames (a WELCOME, a GRANT, a guessed CHALLENGE,
#: a REFUSE...), raw bytes, a frame cut short, or nothing (it closes).
server_answers = st.one_of(
    st.lists(server_frames, min_size=1, max_size=3).map(b"".join),
    st.binary(max_size=48),
    server_frames.flatmap(lambda f: st.integers(1, len(f) - 1).map(lambda n: f[:n])),
)


@hypothesis.settings(
    max_examples=3,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(hypothesis.HealthCheck),
)
@hypothesis.given(answers=st.lists(server_answers, min_size=6, max_size=6))
def test_a_participant_with_a_token_tells_an_impostor_nothing(
    tmp_path_factory: pytest.TempPathFactory, answers: list[bytes]
) -> None:
    from evclock.remote._participant import RemoteClockSource

    folder = tmp_path_factory.mktemp("impostor")
    path = folder / "impostor.sock"
    impostor = spawn(folder, IMPOSTOR, str(path), json.dumps([a.hex() for a in answers]))
    try:
        assert read_line(impostor) == "ready\n"
        failures = []
        for i in range(len(answers)):
            url = f"unix://{path}?name=p{i}&token={TOKEN}&timeout=0.5"
            with pytest.raises(evclock.EvClockError) as failed:
                RemoteClockSource(url)
            failures.append(type(failed.value).__name__)
    finally:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as stop:
            stop.connect(str(path))
            stop.sendall(proto.hello(proto.MODE_LOCKSTEP, "stop", proto.new_nonce()))
    code, out, err = finish(impostor)
    assert code == 0, err
    # Not one byte after the HELLO (no PROOF, no data), whatever the impostor answered.
    assert set(json.loads(out).values()) <= {0}, out
    assert set(failures) <= {"JoinRefusedError", "ClockLostError", "ProtocolError"}, failures
