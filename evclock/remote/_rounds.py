"""Rounds and holds: how joined participants hold sim time, and get it.

While lockstep participants work at time ``t`` the server holds sim time exactly like an
executor job does (the loop's hold count), and their next deadlines are ordinary entries of
the loop's timer heap. So physics cannot advance while a participant works, nor past a
participant's deadline, and a participant with no deadline due in a step costs nothing in
that step.

Participants' deadlines are grouped by time: one loop timer per distinct deadline grants
every participant due then, in join order (so a round of N participants costs one timer, not
N), and the round holds sim time once, however many participants work in it. The round's
data is delivered when its last participant is done (``_routing``), before the hold is
released.

A time jump of the simulation (a jump handler on its clock) delivers the open round's data,
cancels every participant's deadline and sends a numbered JUMP to all of them: each clock
jumps alike, lockstep participants work at the new time, and DONEs sent before a
participant read the JUMP (until its JUMPED) are ignored.

Followers never hold sim time: they get it at their deadlines, at every physics step of a
stepping source, and in keepalives.
"""

from __future__ import annotations

import logging
import operator
import time
from typing import Final

from evclock._errors import ProtocolError
from evclock.kernel._jumps import TimeJump
from evclock.remote import _protocol as proto
from evclock.remote._core import ServerCore
from evclock.remote._peer import Peer

log = logging.getLogger("evclock.remote")
_BY_INDEX: Final = operator.attrgetter("index")


class Rounds(ServerCore):
    """The clock server's lockstep rounds, holds, deadlines, jumps and followers' time."""

    # ------------------------------------------------------------ holds

    def _hold(self) -> None:
        # The loop's exact hold count (SimEventLoop._add_hold): sim time
        # stays put while a participant works, as for an executor job.
        self._loop._add_hold()
        self._holds += 1

    def _release(self) -> None:
        self._holds -= 1
        self._loop._release_hold(None)

    def _release_all_holds(self) -> None:
        while self._holds:
            self._release()

    # ------------------------------------------------------------ lockstep rounds

    def _start_work(self, peer: Peer, now: int) -> None:
        peer.working_at = now
        peer.working_since = time.monotonic()
        peer.silent_reported = False
        if not self._working:
            self._hold()  # one hold per round, however many participants work in it
        self._working += 1

    def _stop_work(self, peer: Peer) -> None:
        peer.working_at = peer.working_since = None
        self._working -= 1
        if not self._working:
            self._close_round()  # may grant again (data arrived): the round then goes on
            self._release()  # after the round closed: physics cannot move in between

    def _on_deadline(self, t_ns: int) -> None:
        _, peers = self._due.pop(t_ns)
        if len(peers) > 1:
            peers.sort(key=_BY_INDEX)  # join order, whatever the DONEs' order
        now = self._kernel.now_ns
        grant = None
        wall = time.monotonic()
        for peer in peers:
            peer.deadline = None
            if peer.mode == proto.MODE_LOCKSTEP:
                if peer.working_at is not None:
                    continue  # already granted now (data arrived): its DONE names its next one
                # _start_work, inline (the hot path of a round)
                peer.working_at = now
                peer.working_since = wall
                peer.silent_reported = False
                if not self._working:
                    self._hold()  # one hold per round, however many participants work in it
                self._working += 1
                if grant is None:
                    grant = proto.grant(now)
                self._send(peer, grant)
            else:
                self._send_time(peer, now)

    def _on_done(self, peer: Peer, t_ns: int, next_ns: int) -> None:
        if peer.jump_acked != peer.jump_sent:
            return  # sent before it read the JUMP: about a time that no longer exists
        now = self._kernel.now_ns
        if peer.mode == proto.MODE_FOLLOW:
            self._schedule(peer, next_ns, now)
            return
        if peer.working_at != t_ns:
            raise ProtocolError(f"DONE at {t_ns} ns, but the participant was granted {now} ns")
        if next_ns != proto.NO_DEADLINE and next_ns <= t_ns:
            raise ProtocolError(f"next deadline {next_ns} ns is not after {t_ns} ns")
        if peer.deadline is None and next_ns > now:  # _schedule's common case, inline
            peer.deadline = next_ns
            due = self._due.get(next_ns)
            if due is not None:
                due[1].append(peer)
            else:
                # SimEventLoop.call_at_ns: exact integer ns, no float round trip.
                timer = self._loop.call_at_ns(next_ns, self._on_deadline, next_ns)
                self._due[next_ns] = (timer, [peer])
        else:
            self._schedule(peer, next_ns, now)
        peer.working_at = peer.working_since = None  # _stop_work, inline
        self._working -= 1
        if not self._working:
            self._close_round()  # may grant again (data arrived): the round then goes on
            self._release()  # after the round closed: physics cannot move in between

    def _schedule(self, peer: Peer, next_ns: int, now: int) -> None:
        if peer.deadline is not None:  # superseded by the deadline the participant just named
            self._unschedule(peer)
        if next_ns == proto.NO_DEADLINE:
            return
        if next_ns <= now:  # a follower behind the simulation: tell it the time now
            self._send_time(peer, now)
            return
        peer.deadline = next_ns
        due = self._due.get(next_ns)
        if due is not None:
            due[1].append(peer)
            return
        # SimEventLoop.call_at_ns: exact integer ns, no float round trip.
        timer = self._loop.call_at_ns(next_ns, self._on_deadline, next_ns)
        self._due[next_ns] = (timer, [peer])

    def _unschedule(self, peer: Peer) -> None:
        if peer.deadline is None:
            return
        timer, peers = self._due[peer.deadline]
        peers.remove(peer)
        if not peers:
            timer.cancel()
            del self._due[peer.deadline]
        peer.deadline = None

    # ------------------------------------------------------------ time jumps

    def _on_jumped(self, peer: Peer, seq: int) -> None:
        if not peer.jump_acked < seq <= peer.jump_sent:
            raise ProtocolError(f"JUMPED {seq}, but jump {peer.jump_sent} was the last sent")
        peer.jump_acked = seq

    def _before_jump(self, jump: TimeJump) -> None:
        """Data of the open round is delivered before the jump, at the time it was sent
        (as an in-process subscriber would have received it before the jump)."""
        if self._round_has_data:
            self._round_has_data = False
            self._deliver_round([])  # everyone runs again after the jump anyway

    def _after_jump(self, jump: TimeJump) -> None:
        """Every participant's clock jumps alike, in order with the data sent before it:
        a lockstep participant works at the new time (its sleeps were woken with
        ClockJumpedError, as in-process), a follower asks for its deadline again."""
        self._jumps += 1
        seq = self._jumps
        after = self._kernel.now_ns
        frame = proto.jump(seq, jump.before.nanoseconds, after)
        for timer, _ in self._due.values():
            timer.cancel()
        self._due.clear()
        for peer in self._peers:
            peer.deadline = None
            if peer.lost:
                continue
            peer.jump_sent = seq
            self._send(peer, frame)
            if peer.mode == proto.MODE_LOCKSTEP:
                if peer.working_at is None:
                    self._start_work(peer, after)
                else:
                    peer.working_at = after
                    peer.working_since = time.monotonic()
        log.info("clock server: sim time jumped %s", jump)

    # ------------------------------------------------------------ followers and keepalives

    def _send_time(self, peer: Peer, now: int) -> None:
        if peer.out:
            peer.stale_time = True  # it is behind: it gets the newest time once it reads
            # Its backlog goes now if its socket takes it (it read since): while physics
            # runs flat out nothing else may poll the socket for a while.
            self._on_writable(peer)
        else:
            self._send(peer, proto.time_frame(now))

    def _tick_followers(self) -> None:
        now = self._kernel.now_ns
        for peer in self._peers:
            if peer.mode == proto.MODE_FOLLOW and not peer.lost:
                self._send_time(peer, now)

    def _add_step_hook(self) -> None:
        # A stepping source (PyBullet) tells every step; on virtual time followers get the
        # time at their own deadlines and whenever they ask (DONE with a past deadline).
        add = getattr(self._loop.source, "add_step_hook", None)
        if add is not None and self._step_hook is None:
            self._step_hook = add(self._tick_followers, when="after")

    def _remove_step_hook(self) -> None:
        if self._step_hook is not None:
            self._step_hook.remove()
            self._step_hook = None

    def _keepalive(self) -> None:
        """Tell every waiting participant the time: a stopped server is one that goes quiet.

        The server's own holds are bounded by the server (the join timeout, ``step_timeout``,
        the ``pause`` policy waiting for a replacement): they are not a stall of the loop, so
        the loop's ``stall_timeout`` starts again while one of them is what holds time.
        """
        if self._join_deadline is not None or (
            self._holds and (self._step_timeout is not None or any(p.lost for p in self._peers))
        ):
            self._loop_bound_restarts()
        now = self._kernel.now_ns
        frame = proto.time_frame(now)
        for peer in self._peers:
            if peer.working_at is None and not peer.lost and not peer.out:
                self._send(peer, frame)

    def _loop_bound_restarts(self) -> None:
        # The server's holds in force are bounded by the server: not a stall of the loop.
        self._loop._restart_stall_bound()
