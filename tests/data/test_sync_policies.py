"""Property tests of the matching policies against brute-force references on small inputs.

The ApproximateTime properties are the ones ROS's documentation states for the C++ policy:
messages used at most once, sets do not cross, sets are contiguous, sets have minimal size
among the sets contiguous to the previous one, and the output depends only on the stamps.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evclock.data._policies import ApproximatePolicy, ExactPolicy, Group, SlopPolicy

FLUSH = 10_000
"""A stamp after every generated one: a final set at it forces every earlier set out."""

Streams = list[list[int]]


@st.composite
def streams_and_order(draw: st.DrawFn, max_len: int = 6) -> tuple[Streams, list[int]]:
    """Per-stream strictly increasing stamps, and an arrival order preserving each stream's."""
    n = draw(st.integers(2, 3))
    streams = [sorted(draw(st.sets(st.integers(0, 40), max_size=max_len))) for _ in range(n)]
    labels = [i for i, stream in enumerate(streams) for _ in stream]
    return streams, draw(st.permutations(labels))


def feed(policy: ExactPolicy | ApproximatePolicy | SlopPolicy, streams: Streams, order: list[int]):
    """Deliver the messages (items are ``(stream, index)``); return groups and emission times."""
    position = [0] * len(streams)
    groups: list[Group] = []
    emitted_at: list[int] = []
    for arrival, stream in enumerate(order):
        index = position[stream]
        position[stream] += 1
        new = policy.add(stream, streams[stream][index], (stream, index))
        groups += new
        emitted_at += [arrival] * len(new)
    return groups, emitted_at


def with_flush(streams: Streams, order: list[int]) -> tuple[Streams, list[int]]:
    n = len(streams)
    return [[*s, FLUSH] for s in streams], [*order, *range(n)]


def without_flush_group(groups: list[Group], streams: Streams) -> list[Group]:
    return [g for g in groups if streams[0][g[0][1]] != FLUSH]  # type: ignore[index]


def indices(group: Group) -> list[int]:
    return [item[1] for item in group]  # type: ignore[index]


def with_previous(groups: list[Group], n: int) -> Iterator[tuple[list[int], list[int]]]:
    """Each group's message indices per stream, after the previous group's (-1s at first)."""
    previous = [-1] * n
    for group in groups:
        current = indices(group)
        yield previous, current
        previous = current


def stamps_of(group: Group, streams: Streams) -> list[int]:
    return [streams[s][i] for s, i in group]  # type: ignore[misc]


def conservation(policy: ExactPolicy | ApproximatePolicy | SlopPolicy, groups, received) -> None:
    used = len(groups) * len(policy.dropped)
    assert used + sum(policy.dropped) + policy.pending == received


def check_approximate_properties(streams: Streams, groups: list[Group]) -> None:
    """Used once, no crossing, contiguous, minimal size: brute force over the known messages."""
    n = len(streams)
    previous = [-1] * n
    for group in groups:
        assert [item[0] for item in group] == list(range(n))  # type: ignore[index]
        current = indices(group)
        # Used at most once and sets do not cross: strictly later on every stream.
        assert all(current[i] > previous[i] for i in range(n))
        # Contiguous: on some stream, no message between the two sets.
        assert any(current[i] == previous[i] + 1 for i in range(n))
        # Minimal size among the sets contiguous to the previous one.
        best = min(
            max(streams[i][c[i]] for i in range(n)) - min(streams[i][c[i]] for i in range(n))
            for c in itertools.product(*(range(previous[i] + 1, len(streams[i])) for i in range(n)))
            if any(c[i] == previous[i] + 1 for i in range(n))
        )
        size = max(stamps_of(group, streams)) - min(stamps_of(group, streams))
        assert size == best
        previous = current


@settings(max_examples=150, deadline=None)
@given(streams_and_order())
def test_approximate_sets_are_used_once_non_crossing_contiguous_and_minimal(case) -> None:
    streams, order = case
    policy = ApproximatePolicy(len(streams), queue_size=100)
    groups, _ = feed(policy, streams, order)
    check_approximate_properties(streams, groups)
    conservation(policy, groups, len(order))


@settings(max_examples=150, deadline=None)
@given(streams_and_order(), st.randoms(use_true_random=False))
def test_approximate_output_depends_only_on_stamps_not_arrival_order(case, rng) -> None:
    streams, order = with_flush(*case)
    other = order[: -len(streams)]
    rng.shuffle(other)
    other += order[-len(streams) :]
    first, _ = feed(ApproximatePolicy(len(streams), 100), streams, order)
    second, _ = feed(ApproximatePolicy(len(streams), 100), streams, other)
    assert first == second
    check_approximate_properties(streams, without_flush_group(first, streams))
    assert first[-1] == tuple((i, len(s) - 1) for i, s in enumerate(streams))


@settings(max_examples=100, deadline=None)
@given(streams_and_order())
def test_lower_bounds_publish_sooner_without_changing_the_sets(case) -> None:
    streams, order = with_flush(*case)
    bounds = [min((b - a for a, b in itertools.pairwise(s)), default=0) for s in streams]
    plain, plain_at = feed(ApproximatePolicy(len(streams), 100), streams, order)
    bounded, bounded_at = feed(
        ApproximatePolicy(len(streams), 100, lower_bounds_ns=bounds), streams, order
    )
    assert bounded == plain
    assert all(b <= p for b, p in zip(bounded_at, plain_at, strict=True))


def test_lower_bounds_prove_a_set_before_the_next_message_arrives() -> None:
    plain = ApproximatePolicy(2, 10)
    bounded = ApproximatePolicy(2, 10, lower_bounds_ns=[10, 10])
    for policy in (plain, bounded):
        assert policy.add(0, 0, "a0") == []
        assert policy.add(0, 10, "a10") == []
        assert policy.add(1, 1, "b1") == [("a0", "b1")]
    # Is (a10, b12) the best set around b12? An a message at 11 would make a smaller one.
    assert plain.add(1, 12, "b12") == []  # so without bounds it waits for a's next message
    assert plain.add(0, 20, "a20") == [("a10", "b12")]
    # With a's messages at least 10 apart, a's next is >= 20: (a10, b12) is proven at once.
    assert bounded.add(1, 12, "b12") == [("a10", "b12")]


@settings(max_examples=100, deadline=None)
@given(streams_and_order(), st.integers(0, 15))
def test_max_interval_never_forms_wider_sets(case, max_interval) -> None:
    streams, order = case
    policy = ApproximatePolicy(len(streams), 100, max_interval_ns=max_interval)
    groups, _ = feed(policy, streams, order)
    for previous, current in with_previous(groups, len(streams)):
        stamps = [streams[stream][index] for stream, index in enumerate(current)]
        assert max(stamps) - min(stamps) <= max_interval
        assert all(c > p for c, p in zip(current, previous, strict=True))
    conservation(policy, groups, len(order))


@settings(max_examples=100, deadline=None)
@given(streams_and_order(), st.sampled_from([0.1, 0.5, 2.0]))
def test_age_penalty_keeps_sets_used_once_non_crossing_and_contiguous(case, penalty) -> None:
    streams, order = case
    policy = ApproximatePolicy(len(streams), 100, age_penalty=penalty)
    groups, _ = feed(policy, streams, order)
    for previous, current in with_previous(groups, len(streams)):
        assert all(c > p for c, p in zip(current, previous, strict=True))
        assert any(c == p + 1 for c, p in zip(current, previous, strict=True))
    conservation(policy, groups, len(order))


def test_age_penalty_prefers_an_earlier_set() -> None:
    # a: 11, 15, 18; b: 4, 16. The smallest set contiguous to the start is (a11, b16), size
    # 5; with age_penalty=1 its end moved 12 later than (a11, b4)'s, which counts as 24 > 7.
    def run(penalty: float) -> list[Group]:
        policy = ApproximatePolicy(2, 10, age_penalty=penalty)
        out: list[Group] = []
        for stream, stamp in ((0, 11), (0, 15), (0, 18), (1, 4), (1, 16), (0, 99), (1, 99)):
            out += policy.add(stream, stamp, stamp)
        return out

    assert run(0.0) == [(11, 16), (99, 99)]
    assert run(1.0) == [(11, 4), (15, 16), (99, 99)]


@pytest.mark.parametrize(
    "policy_factory",
    [
        lambda: ApproximatePolicy(2, 5),
        lambda: ApproximatePolicy(2, 5, max_interval_ns=1),
        lambda: SlopPolicy(2, 5, 3),
        lambda: ExactPolicy(2, 5),
    ],
)
def test_memory_stays_bounded_when_nothing_ever_matches(policy_factory) -> None:
    policy = policy_factory()
    groups = []
    for k in range(1000):
        groups += policy.add(0, 1000 * k, k)  # stream 1 never speaks
        assert policy.pending <= 5
    assert groups == []
    assert policy.dropped == [995, 0]
    conservation(policy, groups, 1000)


def test_approximate_queue_overflow_counts_drops_and_still_matches() -> None:
    policy = ApproximatePolicy(2, 3)
    for k in range(10):
        assert policy.add(0, 10 * k, ("a", k)) == []
    assert policy.dropped == [7, 0]
    assert policy.add(1, 91, ("b", 0)) == []  # an a message at 91 would be better: wait
    assert policy.dropped == [9, 0]  # a7 and a8 can never be better than a9: dropped
    assert policy.add(0, 100, ("a", 10)) == [(("a", 9), ("b", 0))]
    assert policy.pending == 1


@settings(max_examples=100, deadline=None)
@given(streams_and_order(), st.integers(1, 10))
def test_slop_groups_are_within_slop_and_use_each_message_once(case, slop) -> None:
    streams, order = case
    policy = SlopPolicy(len(streams), 100, slop)
    groups, _ = feed(policy, streams, order)
    seen: set[tuple[int, int]] = set()
    for group in groups:
        stamps = stamps_of(group, streams)
        assert max(stamps) - min(stamps) < slop  # strictly below, like ROS Python
        for item in group:
            assert item not in seen
            seen.add(item)  # type: ignore[arg-type]
    conservation(policy, groups, len(order))


def test_slop_pairs_scrambled_equal_stamps_like_ros_python() -> None:
    # ROS Python's own test: two streams of equal stamps, each delivered shuffled.
    for n in range(1, 10):
        policy = SlopPolicy(2, n, 100_000_000)
        firsts = list(range(n))[::-1]
        out: list[Group] = []
        for t in firsts:
            out += policy.add(0, t * 1_000_000_000, ("a", t))
        assert out == []
        for t in firsts[::2] + firsts[1::2]:
            out += policy.add(1, t * 1_000_000_000, ("b", t))
        assert sorted(out) == [(("a", t), ("b", t)) for t in range(n)]


def test_slop_matches_the_nearest_and_can_cross() -> None:
    policy = SlopPolicy(2, 10, 5)
    assert policy.add(0, 0, "a0") == []
    assert policy.add(0, 10, "a10") == []
    assert policy.add(1, 9, "b9") == [("a10", "b9")]  # nearest, not the oldest
    assert policy.add(1, 2, "b2") == [("a0", "b2")]  # an older set after a newer one
    assert policy.out_of_order == [0, 1]


@settings(max_examples=100, deadline=None)
@given(streams_and_order())
def test_exact_groups_share_one_stamp_and_come_in_stamp_order(case) -> None:
    streams, order = case
    policy = ExactPolicy(len(streams), 100)
    groups, _ = feed(policy, streams, order)
    last = -1
    for group in groups:
        stamps = stamps_of(group, streams)
        assert len(set(stamps)) == 1
        assert stamps[0] > last
        last = stamps[0]
    conservation(policy, groups, len(order))


@settings(max_examples=100, deadline=None)
@given(streams_and_order())
def test_exact_in_stamp_order_emits_every_common_stamp(case) -> None:
    streams, _ = case
    arrivals = sorted((t, i) for i, s in enumerate(streams) for t in s)
    policy = ExactPolicy(len(streams), 100)
    groups, _ = feed(policy, streams, [i for _, i in arrivals])
    common = sorted(set.intersection(*(set(s) for s in streams)))
    assert [stamps_of(g, streams)[0] for g in groups] == common


def test_exact_drops_incomplete_older_sets_when_a_newer_one_completes() -> None:
    policy = ExactPolicy(2, 10)
    assert policy.add(0, 5, "a5") == []
    assert policy.add(0, 7, "a7") == []
    assert policy.add(1, 7, "b7") == [("a7", "b7")]
    assert policy.dropped == [1, 0]  # a5 can no longer complete in order
    assert policy.pending == 0
    assert policy.add(0, 7, "again") == []
    assert policy.add(0, 7, "replaced") == []
    assert policy.dropped == [2, 0]  # the same stamp twice: the first is replaced
