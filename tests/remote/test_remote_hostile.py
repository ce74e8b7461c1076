"""Hostile peers, with real processes and sockets: impostor servers, eavesdroppers, floods,
bad requests, rogue reports, missing and stopped participants, a full listen backlog.

Every wait is bounded (``finish``/``read_line``, ``?timeout=``, ``step_timeout``).
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import struct
import sys
from pathlib import Path

import pytest
from _remote_helpers import JOIN_BY_HAND, STEADY, finish, read_line, serve_until_left, spawn

import evclock
from evclock.remote import _admission
from evclock.remote import _protocol as proto
from evclock.remote._address import private_dir
from evclock.remote._server import default_address

#: Listens on argv[1] as if it were the simulation; records every byte a participant sends
#: (to argv[2]) and answers its HELLO with a challenge carrying a made-up proof.
IMPOSTOR = """
import os, socket, sys
from evclock.remote import _protocol as proto
listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
listener.bind(sys.argv[1])
listener.listen(1)
listener.settimeout(30)
print("listening", flush=True)
conn, _ = listener.accept()
conn.settimeout(30)
received = b""
reader = proto.Reader()
while not reader.feed(received):
    received += conn.recv(4096)
conn.sendall(proto.challenge(proto.new_nonce(), os.urandom(32)))
while chunk := conn.recv(4096):
    received += chunk
open(sys.argv[2], "wb").write(received)
"""

#: Relays one connection between argv[1] (where participants connect) and the server at
#: argv[2], writing everything that crossed, both ways, to argv[3]: an eavesdropper.
RELAY = """
import selectors, socket, sys
listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
listener.bind(sys.argv[1])
listener.listen(1)
listener.settimeout(30)
print("listening", flush=True)
client, _ = listener.accept()
server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
server.connect(sys.argv[2])
seen = b""
sel = selectors.DefaultSelector()
sel.register(client, selectors.EVENT_READ, server)
sel.register(server, selectors.EVENT_READ, client)
open_ends = 2
while open_ends:
    events = sel.select(30)
    if not events:
        break
    for key, _ in events:
        data = key.fileobj.recv(65536)
        if not data:
            sel.unregister(key.fileobj)
            key.data.shutdown(socket.SHUT_WR)
            open_ends -= 1
            continue
        seen += data
        key.data.sendall(data)
open(sys.argv[3], "wb").write(seen)
"""


def url_in(tmp_path: Path, name: str = "sim.sock") -> str:
    return f"unix://{tmp_path / name}"


def last_line(text: str) -> str:
    return text.strip().splitlines()[-1]


# ---------------------------------------------------------------- authentication


def test_a_participant_never_sends_its_token_to_an_impostor_server(tmp_path: Path) -> None:
    sock_path = tmp_path / "sim.sock"
    dump = tmp_path / "received.bin"
    impostor = spawn(tmp_path, IMPOSTOR, str(sock_path), str(dump))
    assert read_line(impostor) == "listening\n"
    victim = spawn(
        tmp_path,
        STEADY,
        "1",
        EVCLOCK_CLOCK=f"unix://{sock_path}?name=victim&token=correct-horse-battery-staple&timeout=20",
    )
    code, _, err = finish(victim)
    assert code == 1
    assert last_line(err) == (
        f"evclock.remote.JoinRefusedError: the clock server at unix://{sock_path} could not "
        "prove it knows the token: it is not the simulation you meant (or the tokens "
        "differ); the token was not sent to it"
    )
    code, _, err = finish(impostor)
    assert code == 0, err
    received = dump.read_bytes()
    frames = proto.Reader().feed(received)
    assert [kind for kind, _ in frames] == [proto.HELLO]  # nothing after the HELLO
    assert b"hunter2" not in received


def test_an_eavesdropper_learns_neither_the_token_nor_a_reusable_proof(tmp_path: Path) -> None:
    real = url_in(tmp_path, "real.sock")
    front = tmp_path / "front.sock"
    dump = tmp_path / "seen.bin"
    relay = spawn(tmp_path, RELAY, str(front), real.removeprefix("unix://"), str(dump))
    assert read_line(relay) == "listening\n"
    honest = spawn(
        tmp_path,
        STEADY,
        "2",
        EVCLOCK_CLOCK=f"unix://{front}?name=honest&token=correct-horse-battery-staple",
    )

    serve_until_left(real, "honest", token="correct-horse-battery-staple")
    code, out, err = finish(honest)
    assert code == 0, err
    assert out.split() == ["start", "0", "end", "2000000"]
    assert finish(relay)[0] == 0
    seen = dump.read_bytes()
    assert b"hunter2" not in seen
    # What crossed the wire cannot join again: replaying the participant's frames (its
    # HELLO and PROOF, bound to the nonces of that connection) is refused.

    def replay(address: str) -> bytes:
        # Rebuild the client's half: its HELLO and its PROOF, as recorded.
        client_frames = []
        reader = proto.Reader()
        for kind, payload in reader.feed(seen):
            if kind in (proto.HELLO, proto.PROOF):
                client_frames.append(struct.pack("<IB", len(payload) + 1, kind) + payload)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(30)
            sock.connect(address.removeprefix("unix://"))
            sock.sendall(b"".join(client_frames))
            answer = b""
            while chunk := sock.recv(4096):
                answer += chunk
        return answer

    async def replayed() -> bytes:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(real, token="correct-horse-battery-staple") as server:
            return await loop.run_in_executor(None, replay, server.address)

    frames = proto.Reader().feed(evclock.run(replayed()))
    assert [kind for kind, _ in frames] == [proto.CHALLENGE, proto.REFUSE]
    assert proto.parse_refuse(frames[1][1]) == (
        proto.REFUSE_FINAL,
        "wrong or missing token: join with ?token=... in the clock address (evclock control: "
        "--token-file PATH or EVCLOCK_TOKEN)",
    )


def test_a_participant_refuses_a_server_of_another_user(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    other = os.getuid() + 1

    async def main() -> tuple[int, str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url):
            proc = spawn(tmp_path, STEADY, "1", EVCLOCK_CLOCK=f"{url}?server_uid={other}")
            return await loop.run_in_executor(None, finish, proc)

    code, _, err = evclock.run(main())
    assert code == 1
    assert re.fullmatch(
        rf"evclock\.remote\.JoinRefusedError: the clock server at {re.escape(url)} \(pid "
        rf"{os.getpid()}\) runs as user id {os.getuid()}, not {other}: it is not the "
        r"simulation you meant \(another user's process listening there\?\); nothing was "
        rf"sent to it\. Add \?server_uid={os.getuid()} to the address only if you trust "
        r"that user",
        last_line(err),
    )


def test_the_server_refuses_a_participant_of_another_user(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    admitted = os.getuid() + 1

    async def main() -> tuple[int, str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url, peer_uids=[admitted]):
            proc = spawn(tmp_path, STEADY, "1", EVCLOCK_CLOCK=f"{url}?name=p")
            return await loop.run_in_executor(None, finish, proc)

    code, _, err = evclock.run(main())
    assert code == 1
    assert last_line(err) == (
        f"evclock.remote.JoinRefusedError: the clock server at {url} refused 'p': user id "
        f"{os.getuid()} may not join this clock server (it admits user ids {admitted}; serve "
        "with peer_uids=...)"
    )


def test_tcp_needs_a_token_on_both_sides(tmp_path: Path) -> None:
    async def serve_without() -> None:
        async with evclock.remote.serve("tcp://127.0.0.1:0"):
            pass

    with pytest.raises(evclock.InvalidArgumentError) as caught:
        evclock.run(serve_without())
    assert str(caught.value).startswith(
        "serving on tcp://127.0.0.1:0 needs a shared token (token=... or ?token=... in the "
        "address): any user of the machine can reach a tcp port"
    )
    with pytest.raises(evclock.InvalidArgumentError) as joined:
        evclock.remote.RemoteClockSource("tcp://127.0.0.1:9")
    assert str(joined.value).startswith(
        "joining the clock server at tcp://127.0.0.1:9 over tcp needs its token: add "
        "?token=... to the clock address"
    )


def test_the_default_address_is_in_a_private_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    runtime = tmp_path / "runtime"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    assert default_address() == f"unix://{runtime}/evclock/sim-{os.getpid()}.sock"
    assert (runtime / "evclock").stat().st_mode & 0o777 == 0o700

    monkeypatch.delenv("XDG_RUNTIME_DIR")
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    expected = tmp_path / f"evclock-{os.getuid()}"
    assert private_dir() == str(expected)
    assert expected.stat().st_mode & 0o777 == 0o700

    async def main() -> str:
        async with evclock.remote.serve() as server:  # the default address
            proc = spawn(tmp_path, STEADY, "1", EVCLOCK_CLOCK=f"{server.address}?name=p")
            await server.wait_for_participants("p")
            await server.wait_until_left()
        assert finish(proc)[0] == 0
        return server.address

    assert evclock.run(main()) == f"unix://{expected}/sim-{os.getpid()}.sock"


def test_a_directory_planted_by_someone_else_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    planted = tmp_path / f"evclock-{os.getuid()}"
    planted.mkdir()
    planted.chmod(0o777)  # as another user would leave it for everyone to listen in
    with pytest.raises(evclock.InvalidArgumentError) as caught:
        default_address()
    assert str(caught.value) == (
        f"{planted} is not a private directory of this user (owner uid {os.getuid()}, mode "
        "777, a directory): another user may have created it to intercept clock "
        "connections; remove it, or set XDG_RUNTIME_DIR, or serve on an explicit address in "
        "a directory of yours"
    )
    planted.rmdir()
    planted.symlink_to(tmp_path)  # a link to somewhere else
    with pytest.raises(evclock.InvalidArgumentError, match="not a directory"):
        default_address()


def first_answer(url: str, data: bytes) -> tuple[int, bytes]:
    """Serve on ``url``, send ``data`` to it on a raw connection and read until the server
    hangs up: the kind and payload of the first frame it sent back."""

    def exchange(address: str) -> bytes:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(30)
            sock.connect(address.removeprefix("unix://"))
            sock.sendall(data)
            answer = b""
            while chunk := sock.recv(4096):
                answer += chunk
        return answer

    async def main() -> bytes:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            return await loop.run_in_executor(None, exchange, server.address)

    (kind, payload), *_ = proto.Reader().feed(evclock.run(main()))
    return kind, payload


def test_a_participant_of_the_previous_protocol_gets_a_clear_answer(tmp_path: Path) -> None:
    # The scripted peer of version 2 sent HELLO with its token; the server answers with the
    # versions, and a version-3 participant meeting a version-2 server says so too.
    url = url_in(tmp_path)
    payload = b"EVCLK" + struct.pack("<HB", 2, 0) + b"\x03old" + b"\x00\x00"
    frame = struct.pack("<IB", len(payload) + 1, proto.HELLO) + payload
    kind, refused = first_answer(url, frame)
    assert (kind, proto.parse_refuse(refused)) == (
        proto.REFUSE,
        (
            proto.REFUSE_FINAL,
            "protocol version 2 is not supported: this clock server speaks version 3; run "
            "the same evclock version on both sides",
        ),
    )


# ---------------------------------------------------------------- limits before trust


#: Opens argv[1] connections to the server at argv[2]: half announce a 16 MiB frame and
#: stream junk until the server hangs up, half send one byte and stall (slow clients).
FLOOD = """
import socket, sys
socks = []
for i in range(int(sys.argv[1])):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(30)
    s.connect(sys.argv[2])
    socks.append(s)
    try:
        if i % 2:
            s.sendall(b"\\x00\\x00\\x00\\x01H")  # a 16 MiB HELLO, announced
            for _ in range(64):
                s.sendall(b"x" * 65536)
        else:
            s.sendall(b"\\x05")  # one byte of a header, then nothing
    except OSError:
        pass  # the server hung up on it
print("flooded", flush=True)
import time
time.sleep(120)  # keeps its connections open until the test kills it
"""


def _rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_memory_stays_bounded_under_oversized_and_slow_connections(tmp_path: Path) -> None:
    # Bound (stated in the guide): at most MAX_PENDING connections in their handshake, each
    # buffering at most PRE_AUTH_MAX_FRAME + 4 bytes; a frame announced larger is refused
    # before any of it is read. 200 hostile connections change the server's memory by far
    # less than one 16 MiB frame; an honest participant still joins.
    url = url_in(tmp_path)
    flood = None
    stats: dict[str, int] = {}

    async def main() -> None:
        nonlocal flood
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(url) as server:
            before = _rss_kib()
            flood = spawn(tmp_path, FLOOD, "200", url.removeprefix("unix://"))
            await loop.run_in_executor(None, read_line, flood)
            stats["pending"] = len(server._pending)
            stats["buffered"] = sum(len(p.reader.pending) for p in server._pending)
            honest = spawn(tmp_path, STEADY, "3", EVCLOCK_CLOCK=f"{url}?name=honest")
            await server.wait_for_participants("honest", timeout=40)
            await server.wait_until_left()
            stats["grown_kib"] = _rss_kib() - before
            code, out, err = finish(honest)
            assert code == 0, err
            assert out.split() == ["start", "0", "end", "3000000"]

    try:
        evclock.run(main())
    finally:
        if flood is not None:
            flood.kill()
            finish(flood)
    assert stats["pending"] <= _admission.MAX_PENDING
    assert stats["buffered"] <= _admission.MAX_PENDING * (proto.PRE_AUTH_MAX_FRAME + 4)
    assert stats["grown_kib"] < 16 * 1024


def test_an_oversized_frame_before_the_handshake_is_refused_unread(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    header = struct.pack("<IB", proto.PRE_AUTH_MAX_FRAME + 1, proto.HELLO)
    kind, payload = first_answer(url, header)
    assert kind == proto.REFUSE
    assert proto.parse_refuse(payload)[1] == (
        "not an evclock clock client: bad frame length 4097: the limit of this connection "
        "is 4096 bytes (not an evclock clock peer, a frame too large for the server's "
        "max_frame, or a corrupted stream)"
    )


def test_frames_after_the_handshake_are_capped_by_max_frame(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    big = spawn(
        tmp_path,
        """
        import evclock
        async def main():
            link = evclock.remote.participant()
            try:
                link.publish("data", bytes(10_000))
            except evclock.remote.ProtocolError as exc:
                print(exc, flush=True)
            link.publish("data", bytes(1000))
        evclock.run(main())
        """,
        EVCLOCK_CLOCK=f"{url}?name=big",
    )
    got: list[int] = []

    async def main() -> None:
        async with evclock.remote.serve(url, max_frame=8192) as server:
            server.subscribe("data", lambda m: got.append(len(m.data)))
            await server.wait_for_participants("big")
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(big)
    assert code == 0, err
    assert out.strip() == (
        "a frame of 10014 bytes exceeds the 8192-byte frame limit of this connection; send "
        "large data another way and its key here"
    )
    assert got == [1000]


#: Joins by hand (mode argv[2], no token) and sends one frame of argv[3] bytes' length
#: field, more than the server's max_frame: the server must end this connection only.
OVERSIZED_AFTER_JOIN = (
    JOIN_BY_HAND
    + """
import struct
mode, length = int(sys.argv[2]), int(sys.argv[3])
join(mode, "big")
sock.sendall(struct.pack("<IB", length, proto.PUBLISH) + bytes(64))
while sock.recv(65536):  # until the server hangs up
    pass
print("dropped", flush=True)
"""
)


@pytest.mark.parametrize(
    ("mode", "outcome"),
    [(proto.MODE_FOLLOW, "removed"), (proto.MODE_LOCKSTEP, "aborted")],
)
def test_a_frame_beyond_max_frame_ends_only_that_connection(
    tmp_path: Path, mode: int, outcome: str
) -> None:
    # A follower is removed and the run goes on; a lockstep participant whose stream cannot
    # be read any more is lost, under the fault policy (abort by default).
    url = url_in(tmp_path)
    started = []

    async def main() -> None:
        async with evclock.remote.serve(url, max_frame=8192) as server:
            started.append(
                spawn(
                    tmp_path, OVERSIZED_AFTER_JOIN, url.removeprefix("unix://"), str(mode), "8193"
                )
            )
            await server.wait_for_participants("big")
            started.append(spawn(tmp_path, STEADY, "3", EVCLOCK_CLOCK=f"{url}?name=honest"))
            await server.wait_for_participants("honest")
            await server.wait_until_left("honest")

    if outcome == "removed":
        evclock.run(main())
        code, out, err = finish(started[1])
        assert code == 0, err
        assert out.split() == ["start", "0", "end", "3000000"]
    else:
        with pytest.raises(evclock.remote.ParticipantLostError) as caught:
            evclock.run(main())
        assert caught.value.name == "big"
        assert re.match(
            rf"participant 'big' \(lockstep, pid {started[0].pid}\) broke the protocol framing "
            r"\(bad frame length 8193: the limit of this connection is 8192 bytes",
            str(caught.value),
        )
        for proc in started[1:]:  # the honest one may still be trying to join: stop it
            proc.kill()
            finish(proc)
    code, out, err = finish(started[0])
    assert out.split() == ["joined", "dropped"], err


@pytest.mark.parametrize("max_frame", [0, 100, 2**40, True, "1"])
def test_bad_max_frame_is_refused(max_frame: object) -> None:
    async def main() -> None:
        async with evclock.remote.serve(max_frame=max_frame):  # type: ignore[arg-type]
            pass

    with pytest.raises(evclock.InvalidArgumentError) as caught:
        evclock.run(main())
    assert str(caught.value) == (
        f"max_frame must be a number of bytes from 4096 to 268435456, got {max_frame!r}"
    )


# ---------------------------------------------------------------- the simulation decides


#: Joins in lockstep and sends requests the engine must never see, then honest ones.
BAD_PHYSICS = """
import json, evclock
from evclock.remote._physics import RemotePhysics
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    pb = RemotePhysics(link)
    robot = link.info["robot"]
    results = []
    for bad in (
        lambda: pb.getLinkStates(robot, [99]),          # crashed PyBullet before
        lambda: pb.getJointStates(robot, [0, 99]),
        lambda: pb.getJointState(4242, 0),
        lambda: pb.getLinkState(robot, True),
        lambda: pb.calculateInverseKinematics(robot, 6, [0, 0, "x"]),
        lambda: pb.getBasePositionAndOrientation(robot, flags=1),
        lambda: pb.rayTestBatch([[0, 0, 0]] * 20000, [[0, 0, 1]] * 20000),
        lambda: pb.getEulerFromQuaternion([0, 0, 0]),
    ):
        try:
            bad()
            results.append("answered")
        except evclock.remote.RemoteCallError as exc:
            results.append(str(exc))
    link.publish(
        "pybullet", b'["setJointMotorControl2", [%d, 0, 2], {"targetPosition": NaN}]' % robot
    )
    pb.setJointMotorControlArray(robot, [0, 1], 2, targetPositions=[0.1])
    pb.setJointMotorControl2(robot, 0, 2, targetPosition=0.5)  # an honest one
    await clock.sleep(0.01)
    results.append(pb.getJointState(robot, 0)[0] > 0)  # it moved: the sim still runs
    results.append(list(link.errors))
    print(json.dumps(results), flush=True)
evclock.run(main())
"""


@pytest.mark.pybullet
def test_bad_physics_requests_are_refused_and_the_simulation_goes_on(tmp_path: Path) -> None:
    import pybullet
    import pybullet_data

    from evclock.remote._physics import PhysicsService
    from evclock.sources import PyBulletTimeSource

    url = url_in(tmp_path)
    source = PyBulletTimeSource.connect()
    pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=source.client)
    robot = pybullet.loadURDF("kuka_iiwa/model.urdf", physicsClientId=source.client)
    proc = spawn(tmp_path, BAD_PHYSICS, EVCLOCK_CLOCK=f"{url}?name=bad")

    async def main() -> None:
        async with evclock.remote.serve(url, info={"robot": robot}) as server:
            PhysicsService(source.client).install(server)
            await server.wait_for_participants("bad")
            await server.wait_until_left()

    evclock.run(main(), source=source)
    code, out, err = finish(proc)
    assert code == 0, err
    *answers, moved, errors = json.loads(out)
    prefix = "call to 'pybullet' failed in the simulation: InvalidArgumentError: pybullet."
    assert answers == [
        prefix + "getLinkStates: linkIndices 99 is not a link index of that body (valid: 0 to 6)",
        prefix + "getJointStates: jointIndices 99 is not a joint index of that body (valid: 0 "
        "to 6)",
        prefix + "getJointState: bodyUniqueId 4242 is not the id of a body",
        prefix + "getLinkState: linkIndex must be an integer link index, got True",
        prefix + "calculateInverseKinematics: targetPosition must hold finite numbers, got 'x'",
        prefix + "getBasePositionAndOrientation has no parameter 'flags' served to remote "
        "controllers (served: bodyUniqueId)",
        prefix + "rayTestBatch: rayFromPositions has 20000 items (at most 16384)",
        prefix + "getEulerFromQuaternion: quaternion must have 4 items, got 3",
    ]
    assert moved is True
    assert errors == [
        "frame of kind 'P' refused: the simulation refused data on topic 'pybullet': "
        "InvalidArgumentError: a pybullet request holds NaN: numbers must be finite",
        "frame of kind 'P' refused: the simulation refused data on topic 'pybullet': "
        "InvalidArgumentError: pybullet.setJointMotorControlArray: targetPositions must "
        "have 2 items, got 1",
    ]


#: Joins in lockstep and sends MuJoCo requests that must never touch the MjData, then
#: honest ones through the stand-in the controllers use.
BAD_MUJOCO = """
import json, evclock
from evclock.remote._mujoco_physics import RemoteMjData
from evclock_sims import MuJoCoWorld
from evclock_sims.kuka import JOINT_NAMES
local = MuJoCoWorld()  # the controllers' own copy of the model: the fields' shapes
local.load_urdf("kuka_iiwa/model.urdf", position_joints=JOINT_NAMES)
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    data = RemoteMjData(link, local.data)
    results = []
    for bad in (
        b'["qpos2"]', b'[]', b'[1]', json.dumps(["qpos"] * 14).encode(), b'not json',
        json.dumps(["q" * 100_000]).encode(),
    ):
        try:
            link.call("mujoco", bad)
            results.append("answered")
        except evclock.remote.RemoteCallError as exc:
            results.append(str(exc))
    for bad in (
        b'["qpos", [0], [1.0]]',
        b'["time", [0], [1.0]]',
        b'["ctrl", [0, 1], [0.5]]',
        b'["ctrl", [0], [NaN]]',
        b'["qfrc_applied", [0], [1e308]]',
        b'["ctrl", [7], [0.5]]',
        b'["ctrl", [-1], [0.5]]',
        b'["xfrc_applied", [0, 0], [1, 2]]',
        b'["ctrl", [true], [1]]',
        b'["ctrl", [0, 1, 2, 3, 4, 5, 6, 7], [0, 0, 0, 0, 0, 0, 0, 0]]',
        b'["ctrl", [0], ["x"]]',
        b'["ctrl", 0, 0.5]',
        b'["ctrl", [0]]',
    ):
        link.publish("mujoco", bad)
    data.ctrl[1] = float("nan")  # through the stand-in: the simulation refuses it too
    for local_misuse in (
        lambda: data.qpos.__setitem__(0, 1.0),
        lambda: setattr(data, "ctrl", [0.0] * 7),
        lambda: data.time,
    ):
        try:
            local_misuse()
            results.append("accepted")
        except (evclock.InvalidArgumentError, AttributeError) as exc:
            results.append(f"{type(exc).__name__}: {exc}")
    data.ctrl[0] = 0.5  # honest ones
    data.xfrc_applied[2, 3:] = [0.0, 0.0, 0.25]
    await clock.sleep(0.2)
    xpos, ctrl = data.read("xpos", "ctrl")
    results.append([list(xpos.shape), ctrl.tolist(), data.xfrc_applied[2].tolist()])
    results.append(bool(data.qpos[0] > 0.05))  # it moved: the simulation still runs
    results.append(list(link.errors))
    print(json.dumps(results), flush=True)
evclock.run(main())
"""


def test_bad_mujoco_requests_are_refused_and_the_simulation_goes_on(tmp_path: Path) -> None:
    from evclock.remote._mujoco_physics import READS, WRITES, MjDataService
    from evclock_sims import MuJoCoWorld
    from evclock_sims.kuka import JOINT_NAMES

    url = url_in(tmp_path)
    world = MuJoCoWorld()
    world.load_urdf("kuka_iiwa/model.urdf", position_joints=JOINT_NAMES)
    source = world.time_source()
    proc = spawn(tmp_path, BAD_MUJOCO, EVCLOCK_CLOCK=f"{url}?name=bad")

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            MjDataService(world.data).install(server)
            await server.wait_for_participants("bad")
            await server.wait_until_left()

    evclock.run(main(), source=source)
    code, out, err = finish(proc)
    assert code == 0, err
    *answers, misuse_1, misuse_2, misuse_3, written, moved, errors = json.loads(out)
    failed = "call to 'mujoco' failed in the simulation: "
    readable = ", ".join(READS)
    writable = ", ".join(WRITES)
    assert answers == [
        f"{failed}InvalidArgumentError: mujoco.qpos2 is not served to controllers in another "
        f"process (readable: {readable})",
        f"{failed}InvalidArgumentError: a mujoco read is a list of field names (readable: "
        f"{readable})",
        f"{failed}InvalidArgumentError: a mujoco read names a field by a string, got 1",
        f"{failed}InvalidArgumentError: a mujoco read names at most 13 fields, got 14",
        f"{failed}ProtocolError: a mujoco request is not JSON",
        f"{failed}InvalidArgumentError: mujoco.'{'q' * 200}'... (99800 more characters not "
        f"shown) is not served to controllers in another process (readable: {readable})",
    ]
    assert [misuse_1, misuse_2, misuse_3] == [
        "InvalidArgumentError: mujoco.qpos is read-only to controllers in another process "
        f"(writable: {writable})",
        "InvalidArgumentError: MjData.ctrl cannot be replaced from another process: assign "
        f"into a writable field instead (data.ctrl[:] = values; writable: {writable})",
        "AttributeError: MjData.time is not available to controllers in another process; they "
        f"may read {readable} and write {writable}",
    ]
    nbody = world.model.nbody
    assert written == [[nbody, 3], [0.5, 0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0.25]]
    assert moved is True
    refused = "frame of kind 'P' refused: the simulation refused data on topic 'mujoco': "
    assert errors == [
        refused + "InvalidArgumentError: " + message
        for message in (
            f"mujoco.qpos is read-only to controllers in another process (writable: {writable})",
            f"mujoco.time is not served to controllers in another process (writable: {writable})",
            "mujoco.ctrl: 2 indices but 1 values",
            "a mujoco request holds NaN: numbers must be finite",
            "mujoco.qfrc_applied: values must be finite numbers, got 1e+308",
            "mujoco.ctrl: index 7 is out of range: the model's ctrl has 7 values (valid: 0 to 6)",
            "mujoco.ctrl: index -1 is out of range: the model's ctrl has 7 values (valid: 0 to 6)",
            "mujoco.xfrc_applied: index 0 is given twice",
            "mujoco.ctrl: an index must be an integer, got True",
            "mujoco.ctrl: 8 indices for a field of 7 values",
            "mujoco.ctrl: values must be finite numbers, got 'x'",
            "mujoco.ctrl: indices and values must be lists",
        )
    ] + [
        refused + "ProtocolError: a mujoco write is not [field, indices, values] JSON",
        refused + "InvalidArgumentError: a mujoco request holds NaN: numbers must be finite",
    ]
    # Nothing refused reached the simulation's data: only the honest writes did.
    assert world.data.ctrl.tolist() == [0.5, 0, 0, 0, 0, 0, 0]
    assert not world.data.qfrc_applied.any()
    assert world.data.xfrc_applied.reshape(-1).nonzero()[0].tolist() == [2 * 6 + 5]


#: A lockstep participant that is not the controllers publishes a report saying the
#: mission succeeded, then leaves; a follower stays joined until the simulation ends.
ROGUE = """
import json, evclock
async def main():
    link = evclock.remote.participant()
    print("joined", flush=True)
    link.publish("evclock.report", json.dumps({"success": True, "finished": True,
        "summary": {"forged": 1}, "loops": []}).encode())
    await evclock.clock().sleep(0.001)  # once the controllers joined and time moves
    print(json.dumps(list(link.errors)), flush=True)
evclock.run(main())
"""

LINGERING_FOLLOWER = """
import evclock
async def main():
    clock = evclock.clock()
    print("joined", flush=True)
    try:
        await clock.sleep(10_000)
    except evclock.ClockLostError:
        pass
try:
    evclock.run(main())
except evclock.ClockLostError as exc:
    print("lost:", exc, flush=True)
"""


@pytest.mark.pybullet
def test_only_the_controllers_report_and_a_follower_changes_nothing(tmp_path: Path) -> None:
    from test_remote_split import evclock_cli, wait

    from evclock.tools._cli import run_scenario

    address = f"unix://{tmp_path / 'sim.sock'}"
    server = evclock_cli(
        "run", "cartpole", "--until", "2", "--rtf", "max", "--quiet", "--seed", "3",
        "--serve", address, "--remote-controllers", "--json", str(tmp_path / "sim.json"),
    )  # fmt: skip
    follower = spawn(
        tmp_path, LINGERING_FOLLOWER, EVCLOCK_CLOCK=f"{address}?name=watch&mode=follow"
    )
    assert read_line(follower) == "joined\n"
    rogue = spawn(tmp_path, ROGUE, EVCLOCK_CLOCK=f"{address}?name=rogue")
    assert read_line(rogue) == "joined\n"
    controllers = evclock_cli(
        "control", "cartpole", "--until", "2", "--quiet", "--seed", "3", "--clock", address
    )
    code, out, err = finish(rogue)
    assert code == 0, err
    assert json.loads(out.splitlines()[-1]) == [
        "frame of kind 'P' refused: the simulation refused data on topic 'evclock.report': "
        "InvalidArgumentError: only the controllers ('controllers') hand over the run's "
        "report, not 'rogue'"
    ]
    assert wait(controllers)[0] in (0, 1, 3)
    sim_code, output = wait(server)  # ends although the follower is still joined
    assert sim_code in (0, 1, 3), output
    finish(follower)
    split = json.loads((tmp_path / "sim.json").read_text())
    assert "forged" not in split["summary"]
    local = run_scenario("cartpole", until=2.0, rtf=None, seed=3).to_json()
    assert split["final_state"] == local["final_state"]
    assert split["summary"] == local["summary"]
    assert split["sim_time_s"] == local["sim_time_s"]


# ---------------------------------------------------------------- liveness


def test_a_missing_participant_is_participant_lost_not_a_stall(tmp_path: Path) -> None:
    url = url_in(tmp_path)

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("ghost", timeout=3.0)

    with pytest.raises(evclock.remote.ParticipantLostError) as caught:
        evclock.run(main(), stall_timeout=1.0)  # the server's own bound decides
    assert caught.value.name == "ghost"  # bare, as everywhere else (it was "'ghost'")
    assert str(caught.value) == (
        f"'ghost' did not join {url} in time; start them with clock='{url}' (or EVCLOCK_CLOCK)"
    )


def test_participant_lost_names_the_first_missing_participant_bare(tmp_path: Path) -> None:
    url = url_in(tmp_path)

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            await server.wait_for_participants("never-comes", "nor-this-one", timeout=1.0)

    with pytest.raises(evclock.remote.ParticipantLostError) as caught:
        evclock.run(main(), stall_timeout=1.0)
    assert caught.value.name == "never-comes"
    assert str(caught.value).startswith(
        f"'never-comes', 'nor-this-one' did not join {url} in time; "
    )


def test_a_stopped_participant_is_lost_within_step_timeout_not_stall_timeout(
    tmp_path: Path,
) -> None:
    url = url_in(tmp_path)
    stuck = spawn(
        tmp_path,
        """
        import evclock, os, signal
        async def main():
            clock = evclock.clock()
            await clock.sleep(0.002)
            print("stopping", flush=True)
            os.kill(os.getpid(), signal.SIGSTOP)
        evclock.run(main())
        """,
        EVCLOCK_CLOCK=f"{url}?name=frozen",
    )

    async def main() -> None:
        async with evclock.remote.serve(url, step_timeout=2.5) as server:
            await server.wait_for_participants("frozen")
            await server.wait_until_left()

    try:
        with pytest.raises(evclock.remote.ParticipantLostError) as caught:
            evclock.run(main(), stall_timeout=1.0)
    finally:
        stuck.send_signal(signal.SIGKILL)
        finish(stuck)
    assert caught.value.name == "frozen"
    assert re.fullmatch(
        rf"participant 'frozen' \(lockstep, pid {stuck.pid}\) did not finish its step within "
        r"step_timeout=2\.5 s of wall time \(stopped or stuck\) at 0\.002000 s of sim time \(it "
        r"was last granted 0\.002000 s of sim time and had not answered for [2-9]\.[0-9] s of "
        r"wall time\); the simulation was aborted .*",
        str(caught.value),
    )


#: Waits (bounded) for the file argv[1] to exist, then 2 s more, and drops argv[1].
WAIT_FOR_MARKER = """
import os, sys, time
marker = sys.argv.pop(1)
deadline = time.monotonic() + 30
while not os.path.exists(marker) and time.monotonic() < deadline:
    time.sleep(0.02)
time.sleep(2.0)  # the simulation stays paused longer than its stall_timeout
"""


def test_pause_waits_for_a_replacement_beyond_stall_timeout(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    marker = tmp_path / "died"
    first = spawn(
        tmp_path,
        """
        import evclock, os, signal, sys
        async def main():
            await evclock.clock().sleep(0.002)
            open(sys.argv[1], "w").close()
            os.kill(os.getpid(), signal.SIGKILL)
        evclock.run(main())
        """,
        str(marker),
        EVCLOCK_CLOCK=f"{url}?name=worker",
    )
    replacement = spawn(
        tmp_path,
        WAIT_FOR_MARKER + STEADY,
        str(marker),
        "2",
        EVCLOCK_CLOCK=f"{url}?name=worker",
    )

    async def main() -> None:
        async with evclock.remote.serve(url, on_fault="pause") as server:
            await server.wait_for_participants("worker")
            await server.wait_until_left()

    evclock.run(main(), stall_timeout=1.0)
    finish(first)
    code, out, err = finish(replacement)
    assert code == 0, err
    assert out.split() == ["start", "2000000", "end", "4000000"]


def test_a_full_listen_backlog_is_retried_until_the_join_timeout(tmp_path: Path) -> None:
    url = url_in(tmp_path)
    path = url.removeprefix("unix://")
    waiting = spawn(
        tmp_path,
        """
        import logging, sys, evclock
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)
        print("joining", flush=True)
        async def main():
            print("joined", evclock.clock().now().nanoseconds, flush=True)
        evclock.run(main())
        """,
        EVCLOCK_CLOCK=f"{url}?name=late&timeout=30",
    )
    assert read_line(waiting) == "joining\n"
    fillers: list[socket.socket] = []

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            # The loop does not accept while this block runs: fill its backlog, then keep
            # it full until the participant has met it at least once.
            while True:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.setblocking(False)
                try:
                    sock.connect(path)
                except BlockingIOError:
                    sock.close()
                    break
                fillers.append(sock)
            assert waiting.stderr is not None
            # Bounded: the participant retries for 30 s, then ends (EOF).
            while line := waiting.stderr.readline():
                if "listen backlog full" in line:
                    break
            assert "listen backlog full; retrying in" in line, line
            for sock in fillers:
                sock.close()
            await server.wait_for_participants("late")
            await server.wait_until_left()

    evclock.run(main())
    code, out, err = finish(waiting)
    assert code == 0, err
    assert out.split() == ["joined", "0"]


if sys.platform != "linux":  # SO_PEERCRED, /proc
    pytestmark = pytest.mark.skip(reason="Linux only")
