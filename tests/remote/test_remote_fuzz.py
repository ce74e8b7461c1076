"""Fuzzing the clock server: an authenticated participant sends random and mutated frames.

Hypothesis makes the frames; a real participant process sends them over a real socket
while two honest lockstep participants and the simulation exchange data and calls. The
simulation must neither crash nor hang, every frame of a kind a participant never sends
is answered with an ERROR naming it, and the honest participants' runs and the
simulation's record stay bit-identical to a run without the fuzzer.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from _remote_helpers import finish, spawn

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

#: Joins by hand (the handshake with the token), sends the frames in argv[2] (a JSON
#: list of hex strings) one by one, answering grants meanwhile, finishes its step, leaves.
FUZZER = """
import json, os, select, socket, sys, time
from evclock.remote import _protocol as proto
path, frames, mode = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
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
frames = st.lists(st.one_of(valid_frames, mutated(), random_frames), min_size=1, max_size=25)


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
                fuzzer = spawn(
                    tmp_path,
                    FUZZER,
                    url.removeprefix("unix://"),
                    json.dumps([frame.hex() for frame in fuzz]),
                    str(mode),
                    TOKEN=TOKEN,
                )
            # One after the other: data of one time is delivered in join order.
            for me, other, step in (("a", "b", "0.001"), ("b", "a", "0.0015")):
                honest.append(
                    spawn(
                        tmp_path,
                        HONEST,
                        me,
                        other,
                        step,
                        EVCLOCK_CLOCK=f"{url}?name={me}&token={TOKEN}",
                    )
                )
                await server.wait_for_participants(me, timeout=30)
            await server.wait_until_left("a", "b")
            record.append(["end", clock.now().nanoseconds])

    evclock.run(main())
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
                json.dumps([f.hex() for f in frames]),
                str(proto.MODE_FOLLOW),
                TOKEN=TOKEN,
            )
            await server.wait_for_participants("fuzzer")
            await server.wait_until_left()
        code, out, err = finish(proc)
        assert code == 0, err
        return out

    assert evclock.run(main()).splitlines() == ["joined", f"[{ord('Q')}]"]
