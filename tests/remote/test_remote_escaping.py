"""Nothing a peer sends reaches a log line or an error frame unescaped or unbounded (issue 34,
defects 7 and 8), and the PyBullet service serves only the parameters of its functions
(defect 11).

A real participant process sends the simulation names and values holding newlines, terminal
escapes and 10 MB; the simulation's log and every answer it sends back are quoted, one line
each and a few hundred characters long.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
from _remote_helpers import finish, spawn

import evclock
from evclock.remote._checks import LINE_CHARS, SHOWN_CHARS, one_line, shown, shown_name
from evclock.remote._mujoco_physics import READS, WRITES, MjDataService

#: What a hostile participant would like the simulation's log to say.
FORGED = "\nclock server: participant 'controllers' (lockstep) left at 1.000000 s\x1b[2K\x1b[1A"
#: 10 MB.
HUGE = 10_000_000
#: The longest message about a peer: the limit of a line, its head and tail.
BOUND = 2 * LINE_CHARS


def url_in(tmp_path: Path) -> str:
    return f"unix://{tmp_path / 'sim.sock'}"


def check_bounded(texts: list[str]) -> None:
    for text in texts:
        assert "\n" not in text, text[:300]
        assert "\x1b" not in text, text[:300]
        assert len(text) < BOUND, text[:300]


def server_log(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("evclock.remote")]


# ---------------------------------------------------------------- the helpers


@pytest.mark.parametrize(
    "value",
    [FORGED, "x" * HUGE, b"\x1b[2J" * HUGE, ["\n"] * 100_000, {"k\n": "\x1b" * HUGE}, 10**4000],
    ids=["forged", "10MB-str", "bytes", "list", "dict", "int"],
)
def test_shown_quotes_and_cuts_what_a_peer_sent(value: object) -> None:
    text = shown(value)
    check_bounded([text])
    assert len(text) < 12 * SHOWN_CHARS


def test_shown_says_how_much_it_cut() -> None:
    assert shown("abc\n") == "'abc\\n'"
    assert shown("y" * 1000) == f"'{'y' * SHOWN_CHARS}'... (800 more characters not shown)"
    assert shown(b"z" * 250) == f"b'{'z' * SHOWN_CHARS}'... (50 more bytes not shown)"


def test_a_plain_name_is_shown_as_it_is_any_other_quoted() -> None:
    assert shown_name("qpos2") == "qpos2"
    for name in ("qpos\n", "q" * 65, "qpos\x1b[0m", "é", 7, "a b"):
        assert shown_name(name) == shown(name)


def test_one_line_escapes_and_bounds_a_message() -> None:
    assert one_line("refused: 'a'\nforged\x1b[0m") == "refused: 'a'\\nforged\\x1b[0m"
    cut = one_line("m" * (LINE_CHARS + 5))
    assert cut == f"{'m' * LINE_CHARS}... (5 more characters not shown)"


# ---------------------------------------------------------------- PyBullet

#: Sends the PyBullet service names and values meant to forge or flood the simulation's log,
#: then an honest command; prints what the simulation answered.
HOSTILE_PYBULLET = """
import json, sys, evclock
from evclock.remote._physics import RemotePhysics
FORGED, HUGE = json.loads(sys.argv[1])
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    pb = RemotePhysics(link)
    robot = link.info["robot"]
    answers = []
    for request in (
        ["getJointState" + FORGED, [robot, 0], {}],
        ["getJointState", [robot, 0], {FORGED: 1}],
        ["calculateInverseKinematics", [robot, 6, [0, 0, "x" * HUGE]], {}],
        ["getJointState", [robot, "\\x1b[31m" * (HUGE // 10)], {}],  # 10 MB of JSON
        ["getJointState", [robot, 0], {"physicsClientId": 0}],
    ):
        try:
            link.call("pybullet", json.dumps(request).encode())
            answers.append("answered")
        except evclock.remote.RemoteCallError as exc:
            answers.append(str(exc))
    for command in (
        ["setJointMotorControl2" + FORGED, [robot, 0, 2], {}],
        ["setJointMotorControl2", [robot, 0, 2], {"targetPosition": "y" * HUGE}],
        ["setJointMotorControl2", [robot, 0, 2], {"targetPosition": 0.5, "physicsClientId": 0}],
    ):
        link.publish("pybullet", json.dumps(command).encode())
    pb.setJointMotorControl2(robot, 0, 2, targetPosition=0.5, physicsClientId=7)  # stripped here
    await clock.sleep(0.01)
    moved = pb.getJointState(robot, 0)[0] > 0
    print(json.dumps([answers, list(link.errors), moved]), flush=True)
evclock.run(main())
"""


@pytest.mark.pybullet
def test_hostile_pybullet_requests_reach_no_log_or_answer_unescaped_or_unbounded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import pybullet
    import pybullet_data

    from evclock.remote._physics import PhysicsService
    from evclock.sources import PyBulletTimeSource

    url = url_in(tmp_path)
    source = PyBulletTimeSource.connect()
    pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=source.client)
    robot = pybullet.loadURDF("kuka_iiwa/model.urdf", physicsClientId=source.client)
    proc = spawn(
        tmp_path, HOSTILE_PYBULLET, json.dumps([FORGED, HUGE]), EVCLOCK_CLOCK=f"{url}?name=bad"
    )

    async def main() -> None:
        async with evclock.remote.serve(url, info={"robot": robot}) as server:
            PhysicsService(source.client).install(server)
            await server.wait_for_participants("bad")
            await server.wait_until_left()

    with caplog.at_level(logging.INFO, logger="evclock.remote"):
        evclock.run(main(), source=source)
    code, out, err = finish(proc)
    assert code == 0, err[-2000:]
    answers, errors, moved = json.loads(out)
    assert moved is True  # the honest command (its own client id left out) was applied
    check_bounded(answers + errors + server_log(caplog))
    failed = "call to 'pybullet' failed in the simulation: InvalidArgumentError: pybullet."
    forged = shown("getJointState" + FORGED)
    cut = HUGE - SHOWN_CHARS
    assert answers == [
        f"{failed}{forged} is not served to remote controllers as a query",
        f"{failed}getJointState has no parameter {shown(FORGED)} served to remote controllers "
        "(served: bodyUniqueId, jointIndex)",
        f"{failed}calculateInverseKinematics: targetPosition must hold finite numbers, got "
        f"'{'x' * SHOWN_CHARS}'... ({cut} more characters not shown)",
        f"{failed}getJointState: jointIndex must be an integer joint index, got "
        f"{shown((chr(27) + '[31m') * (HUGE // 10))}",
        f"{failed}getJointState: physicsClientId is not served: the simulation calls its own "
        "client (a RemotePhysics leaves it out of its requests)",
    ]
    refused = (
        "frame of kind 'P' refused: the simulation refused data on topic 'pybullet': "
        "InvalidArgumentError: pybullet."
    )
    assert errors == [
        f"{refused}{shown('setJointMotorControl2' + FORGED)} is not served to remote "
        "controllers as a command",
        f"{refused}setJointMotorControl2: targetPosition must be a finite number, got "
        f"'{'y' * SHOWN_CHARS}'... ({cut} more characters not shown)",
        f"{refused}setJointMotorControl2: physicsClientId is not served: the simulation calls "
        "its own client (a RemotePhysics leaves it out of its requests)",
    ]
    refusals = [line for line in server_log(caplog) if "refused a frame" in line]
    assert len(refusals) == 3
    assert all(line.startswith("clock server: refused a frame of kind P from 'bad'")
               for line in refusals)  # fmt: skip


# ---------------------------------------------------------------- MuJoCo

HOSTILE_MUJOCO = """
import json, sys, evclock
FORGED, HUGE = json.loads(sys.argv[1])
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    answers = []
    for request in (["qpos" + FORGED], ["q" * HUGE], [["\\x1b" * (HUGE // 6)]]):
        try:
            link.call("mujoco", json.dumps(request).encode())
            answers.append("answered")
        except evclock.remote.RemoteCallError as exc:
            answers.append(str(exc))
    for write in (
        ["ctrl" + FORGED, [0], [1.0]],
        ["ctrl", ["\\n" * (HUGE // 2)], [1.0]],
        ["ctrl", [0], ["z" * HUGE]],
        ["ctrl", [10**4000 // 10**3700], [1.0]],
    ):
        link.publish("mujoco", json.dumps(write).encode())
    await clock.sleep(0.01)
    print(json.dumps([answers, list(link.errors)]), flush=True)
evclock.run(main())
"""


def test_hostile_mujoco_requests_reach_no_log_or_answer_unescaped_or_unbounded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from evclock_sims import MuJoCoWorld
    from evclock_sims.kuka import JOINT_NAMES

    url = url_in(tmp_path)
    world = MuJoCoWorld()
    world.load_urdf("kuka_iiwa/model.urdf", position_joints=JOINT_NAMES)
    proc = spawn(
        tmp_path, HOSTILE_MUJOCO, json.dumps([FORGED, HUGE]), EVCLOCK_CLOCK=f"{url}?name=bad"
    )

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            MjDataService(world.data).install(server)
            await server.wait_for_participants("bad")
            await server.wait_until_left()

    with caplog.at_level(logging.INFO, logger="evclock.remote"):
        evclock.run(main(), source=world.time_source())
    code, out, err = finish(proc)
    assert code == 0, err[-2000:]
    answers, errors = json.loads(out)
    check_bounded(answers + errors + server_log(caplog))
    failed = "call to 'mujoco' failed in the simulation: InvalidArgumentError: "
    readable, writable = ", ".join(READS), ", ".join(WRITES)
    cut = HUGE - SHOWN_CHARS
    assert answers == [
        f"{failed}mujoco.{shown('qpos' + FORGED)} is not served to controllers in another "
        f"process (readable: {readable})",
        f"{failed}mujoco.'{'q' * SHOWN_CHARS}'... ({cut} more characters not shown) is not "
        f"served to controllers in another process (readable: {readable})",
        f"{failed}a mujoco read names a field by a string, got {shown([chr(27) * (HUGE // 6)])}",
    ]
    refused = (
        "frame of kind 'P' refused: the simulation refused data on topic 'mujoco': "
        "InvalidArgumentError: mujoco."
    )
    assert errors == [
        f"{refused}{shown('ctrl' + FORGED)} is not served to controllers in another process "
        f"(writable: {writable})",
        f"{refused}ctrl: an index must be an integer, got {shown(chr(10) * (HUGE // 2))}",
        f"{refused}ctrl: values must be finite numbers, got '{'z' * SHOWN_CHARS}'... "
        f"({cut} more characters not shown)",
        f"{refused}ctrl: index {shown(10**300)} is out of range: the model's ctrl has 7 values "
        "(valid: 0 to 6)",
    ]
    assert world.data.ctrl.tolist() == [0.0] * 7  # nothing refused reached the data


# ---------------------------------------------------------------- the server

#: Joins under a name meant to forge a log line, publishes data that a careless subscriber of
#: the simulation puts in its error, and calls a careless service and a missing one.
HOSTILE_PEER = """
import json, sys, evclock
FORGED, HUGE = json.loads(sys.argv[1])
async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    link.publish("echo", (FORGED + "w" * HUGE).encode())
    answers = []
    for service in ("echo", "echo" + FORGED):
        try:
            link.call(service, (FORGED + "v" * HUGE).encode())
            answers.append("answered")
        except evclock.remote.RemoteCallError as exc:
            answers.append(str(exc))
    await clock.sleep(0.01)
    print(json.dumps([answers, list(link.errors)]), flush=True)
evclock.run(main())
"""


def test_what_a_peer_sent_reaches_the_server_log_and_answers_escaped_and_bounded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    url = url_in(tmp_path)
    name = "evil" + FORGED  # a name is at most 255 bytes: quoted, it cannot forge a line
    proc = spawn(
        tmp_path,
        HOSTILE_PEER,
        json.dumps([FORGED, HUGE]),
        EVCLOCK_CLOCK=f"{url}?name={name.replace(chr(10), '%0A').replace(chr(27), '%1B')}",
    )

    def careless(data: bytes) -> None:  # a simulation's own code, echoing what it got
        raise evclock.InvalidArgumentError(f"cannot use {data.decode()}")

    async def main() -> None:
        async with evclock.remote.serve(url) as server:
            server.subscribe("echo", lambda message: careless(message.data))
            server.provide("echo", careless)  # type: ignore[arg-type]
            await server.wait_for_participants(name)
            await server.wait_until_left()

    with caplog.at_level(logging.INFO, logger="evclock.remote"):
        evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err[-2000:]
    answers, errors = json.loads(out)
    log = server_log(caplog)
    check_bounded(answers + errors + log)
    assert log[0].startswith(f"clock server: {shown(name)} (lockstep, pid ")
    assert len(answers) == 2
    assert answers[1] == (
        f"call to {shown('echo' + FORGED)} failed in the simulation: no service "
        f"{shown('echo' + FORGED)} (known: echo)"
    )
    assert answers[0].startswith(
        "call to 'echo' failed in the simulation: "
        + one_line(f"InvalidArgumentError: cannot use {FORGED}")
    )
    assert answers[0].endswith(" more characters not shown)")
    assert errors[0].startswith(
        "frame of kind 'P' refused: "
        + one_line(f"the simulation refused data on topic 'echo': InvalidArgumentError: "
                   f"cannot use {FORGED}")
    )  # fmt: skip
    assert errors[0].endswith(" more characters not shown)")
    assert len(errors) == 1
