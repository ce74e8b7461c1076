"""ROS 2 over DDS: the cost of /clock every physics step, and a follower's added latency.

Usage: python benchmarks/ros2_dds.py [--seconds 10] [--repeat 3] [--messages 500]

1. **Throughput**: the KUKA scenario (240 Hz physics, its joint controller and planner) runs as
   fast as possible for ``--seconds`` of sim time, without and with a
   :class:`evclock.ros2.Ros2ClockPublisher` over DDS publishing /clock after every step, to a
   plain Cyclone DDS subscriber in another process (every sample crosses the loopback
   interface; it counts them). Reported: physics steps per CPU second of this process for both
   and their ratio (the wall figures beside them). Variants alternate round by round; the best
   round of each is kept.
2. **Latency**: this process publishes ``--messages`` /clock samples 2 ms of wall time apart;
   in another process, first a plain Cyclone DDS reader (the baseline: the DDS delivery), then
   an evclock follower (:class:`evclock.ros2.Ros2ClockSource`, its program sleeping until each
   published time), note ``time.monotonic_ns()`` when each sample is seen (the same clock
   across processes on Linux). Reported: the median and 90th percentile of publish-to-seen for
   both, and the follower's added latency (the difference of the medians).

Every participant is on the loopback interface with multicast off (``CYCLONEDDS_URI`` is set
here), in domain ``ROS_DOMAIN_ID`` (else 42).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

LOOPBACK = (
    '<CycloneDDS xmlns="https://cdds.io/config"><Domain id="any"><General><Interfaces>'
    '<NetworkInterface address="127.0.0.1"/></Interfaces><AllowMulticast>false'
    "</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    '<Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
)
os.environ["CYCLONEDDS_URI"] = LOOPBACK
os.environ.setdefault("ROS_DOMAIN_ID", "42")
os.environ["RMW_IMPLEMENTATION"] = "rmw_cyclonedds_cpp"

from _clock_cost import best_rounds, print_rounds  # noqa: E402

from evclock.ros2 import Ros2ClockPublisher  # noqa: E402

# A plain Cyclone DDS reader of rt/clock with ROS's type names: counts samples until stdin
# closes (throughput), or notes when each arrives (latency, ``seen`` mode).
PLAIN_READER = """
import json, os, sys, threading, time
from cyclonedds.core import ReadCondition, SampleState, ViewState, InstanceState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import make_idl_struct
from cyclonedds.idl import types as t
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
Time_ = make_idl_struct("Time_", "builtin_interfaces::msg::dds_::Time_",
                        {"sec": t.int32, "nanosec": t.uint32})
Clock_ = make_idl_struct("Clock_", "rosgraph_msgs::msg::dds_::Clock_", {"clock": Time_})
dp = DomainParticipant(int(os.environ["ROS_DOMAIN_ID"]))
reader = DataReader(dp, Topic(dp, "rt/clock", Clock_),
                    qos=Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1000)))
ws = WaitSet(dp)
ws.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
seen, count, done = {}, [0], threading.Event()
def read():
    while not done.is_set():
        ws.wait(100_000_000)
        for s in reader.take(1000):
            if getattr(s.sample_info, "valid_data", True):
                count[0] += 1
                seen.setdefault(s.clock.sec * 10**9 + s.clock.nanosec, time.monotonic_ns())
threading.Thread(target=read, daemon=True).start()
print("ready", flush=True)
sys.stdin.read()
done.set()
print(json.dumps({"count": count[0], "seen": seen}), flush=True)
"""

# An evclock follower: its program sleeps until each published time and notes when it woke.
FOLLOWER = """
import json, sys, time
import evclock
from evclock import Time
from evclock.ros2 import Ros2ClockSource
n = int(sys.argv[1])
source = Ros2ClockSource(startup_timeout=60)
print("ready", flush=True)
async def main():
    clk = evclock.clock()
    seen = {}
    for k in range(1, n + 1):
        await clk.sleep_until(Time(0, k * 1_000_000))
        seen[k * 1_000_000] = time.monotonic_ns()
    return seen
seen = evclock.run(main(), source=source)
source.close()
print(json.dumps({"count": len(seen), "seen": seen}), flush=True)
"""


def child(code: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def throughput(seconds: float, repeat: int) -> None:
    reader = child(PLAIN_READER)
    assert reader.stdout is not None
    assert reader.stdin is not None
    assert reader.stdout.readline().strip() == "ready"
    publisher = Ros2ClockPublisher()
    best = best_rounds("kuka", seconds, repeat, publisher)
    published = publisher.sequence_number
    publisher.close()
    reader.stdin.close()
    received = json.loads(reader.stdout.readline())["count"]
    reader.wait()
    print("KUKA, 240 Hz physics, /clock over DDS every step")
    print_rounds(best)
    print(f"samples published {published}, received by the other process {received}")


def latencies(code: str, messages: int, publisher: Ros2ClockPublisher) -> list[int]:
    """Publish 0 until ``code``'s process is ready, then 1..messages ms, 2 ms apart."""
    proc = child(code, str(messages))
    assert proc.stdout is not None
    assert proc.stdin is not None
    ready = False
    os.set_blocking(proc.stdout.fileno(), False)
    deadline = time.monotonic() + 60
    while not ready and time.monotonic() < deadline:
        publisher.publish(0)
        time.sleep(0.01)
        line = proc.stdout.readline()
        ready = line.strip() == "ready"
    os.set_blocking(proc.stdout.fileno(), True)
    time.sleep(0.2)  # the reader's first takes done: what follows is measured
    sent: dict[int, int] = {}
    for k in range(1, messages + 1):
        sent[k * 1_000_000] = time.monotonic_ns()
        publisher.publish(k * 1_000_000)
        time.sleep(0.002)
    proc.stdin.close()
    result = json.loads(proc.stdout.readline())
    proc.wait()
    seen = {int(t): ns for t, ns in result["seen"].items()}
    return [seen[t] - sent[t] for t in sent if t in seen]


def latency(messages: int) -> None:
    publisher = Ros2ClockPublisher()
    plain = latencies(PLAIN_READER, messages, publisher)
    follower = latencies(FOLLOWER, messages, publisher)
    publisher.close()
    print(f"\n/clock publish -> seen in another process, {messages} messages 2 ms apart")
    print(f"{'reader':<22}{'seen':>6}{'median us':>12}{'p90 us':>10}")
    for name, values in (("plain Cyclone DDS", plain), ("evclock follower", follower)):
        values = sorted(values)
        p90 = values[int(0.9 * (len(values) - 1))]
        print(
            f"{name:<22}{len(values):>6}{statistics.median(values) / 1e3:>12.1f}{p90 / 1e3:>10.1f}"
        )
    added = statistics.median(follower) - statistics.median(plain)
    print(f"follower's added latency per message (median): {added / 1e3:.1f} us")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--messages", type=int, default=500)
    args = parser.parse_args()
    throughput(args.seconds, args.repeat)
    latency(args.messages)


if __name__ == "__main__":
    main()
