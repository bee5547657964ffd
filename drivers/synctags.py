"""Which SYNC each position sample answers: the tags behind the matched following-error check.

:class:`SyncTags` is fed by :class:`drivers.cyclic.CyclicIO`'s receive paths (``tag`` per TPDO1,
``settle`` at the end of each poll) and owns ``pos_sync``: for drive ``i`` the SYNC ordinal (1 = the
first bus cycle) its last TPDO1 answers, so that the sample is compared with the command of that very
SYNC, however late it arrived.

Drive ``i`` answers every ``feedback_divider``-th SYNC from its SYNC start value, so the SYNCs it
answers are ``k = phase_i (mod divider)``; each drive's samples come in SYNC order, and the drives of
one bus answer in SYNC order too (one receive queue), so a sample answers the first such SYNC after
its drive's previous sample and not before the bus's last tag. A stall of the drives therefore shifts
nothing; TPDO1s lost on the wire are bridged by the other drives of the bus.

A run of lost frames as long as the divider on one bus would leave the tags behind by whole divider
periods for good, so when a bus keeps pace (``CALM_POLLS`` polls in a row with at most one cycle's
worth of position frames each) its samples are tagged no older than ``divider + 1`` SYNCs. After a
stall (``QUIET_POLLS`` polls without a position frame) the bus is *behind*: no re-anchoring until
its tags trail by at most ``divider + 1`` or the lag stops shrinking over ``CATCHUP_POLLS`` polls
(what is left then is lost frames). Where the transport tells how many of its frames the peer has
not consumed yet (``unread_by_peer`` of :mod:`drivers.framerec`: the simulated drives' rings), that
replaces the guess: the tags of a bus are re-anchored only while its drives have taken every SYNC
but the last two cycles' worth, so a backlog still to come is never taken for lost frames, however
slowly or unevenly it drains. SYNCs lost before a drive shift its phase (not handled). A tag never
names a SYNC not yet sent.
"""
from __future__ import annotations

from typing import Callable, Sequence

#: polls in a row with one cycle's worth of position frames on a bus before its SYNC tags may be
#: re-anchored to the SYNCs just sent
CALM_POLLS = 8
#: polls in a row without a position frame on a bus that count as a stall of its drives
QUIET_POLLS = 16
#: after a stall, a bus's tags are re-anchored only once its backlog no longer shrinks over this many
#: polls (a catch-up at 1.1x the SYNC rate has runs of CALM_POLLS single samples: it looked caught up)
CATCHUP_POLLS = 64


class SyncTags:
    """SYNC tags of the position samples of a bus layout (:func:`drivers.layout.plan_layout`).

    Tags count loop cycles (:attr:`drivers.cyclic.CyclicIO.cycles`); with ``sync_every`` n the bus
    sends SYNC number j with the loop cycle j·n, so a drive answering every d-th SYNC answers every
    d·n-th loop cycle. ``peer_unread``: per bus, ``None`` or a callable giving the records sent on it
    that the drives have not consumed yet; ``max_unread``: per bus, the most of those that still
    counts as keeping pace (records of two bus cycles)."""

    def __init__(self, plan, peer_unread: Sequence[Callable[[], int] | None] | None = None,
                 max_unread: Sequence[int] | None = None, sync_every: int = 1):
        d = max(1, int(plan.feedback_divider))
        s = max(1, int(sync_every))
        nb = plan.buses
        self.div = d * s                              #: loop cycles between a drive's samples
        self.slack = (d + 1) * s                      #: a bus keeping pace trails by no more (loop cycles)
        self.step = s
        self.phase = [((nd.tpdo1_sync_start % d) if plan.sync_counter_overflow else 0) * s for nd in plan.nodes]
        self.bus_of = [nd.bus for nd in plan.nodes]
        self.n = len(plan.nodes)
        self.pos_sync: list[int] = [0] * self.n       #: SYNC answered by each drive's last sample
        self.bus_tag = [0] * nb                       #: newest tag per bus
        self.bus_rx = [0] * nb                        #: position frames per bus in this poll
        self.pace = [plan.tpdo_per_cycle(b) for b in range(nb)]
        self.fresh_mask = 0
        self.calm = [0] * nb
        self.quiet = [0] * nb
        self.behind = [False] * nb                    #: stalled, catching up: no re-anchoring
        self.lag = [0] * nb                           #: SYNCs the bus's last tag trailed at the last check
        self.lag_polls = [0] * nb                     #: polls with frames since that check
        self.peer_unread = list(peer_unread) if peer_unread is not None else [None] * nb
        self.max_unread = list(max_unread) if max_unread is not None else [0] * nb

    def tag(self, i: int, cycles: int) -> None:
        """A TPDO1 of drive ``i`` arrived; ``cycles``: SYNCs sent so far."""
        b = self.bus_of[i]
        d = self.div
        lo = self.bus_tag[b]
        k = self.pos_sync[i] + 1
        if lo > k:
            k = lo
        k += (self.phase[i] - k) % d
        if k > cycles:
            k = cycles - (cycles - self.phase[i]) % d
        self.pos_sync[i] = k
        self.bus_tag[b] = k
        self.bus_rx[b] += 1
        self.fresh_mask |= 1 << i

    def settle(self, cycles: int) -> None:
        """End of a poll: track each bus's pace, and on buses that keep pace (not *behind*) no tag
        older than ``divider + 1`` SYNCs."""
        rx = self.bus_rx
        for b in range(len(rx)):
            self._pace_bus(b, rx[b], cycles)
        if self.fresh_mask:
            self._re_anchor(cycles)
        for b in range(len(rx)):
            rx[b] = 0
        self.fresh_mask = 0

    def _pace_bus(self, b: int, n: int, cycles: int) -> None:
        calm, quiet = self.calm, self.quiet
        if n > self.pace[b]:            # a backlog being drained
            calm[b] = 0
        elif n:
            quiet[b] = 0
            calm[b] += 1
        else:
            quiet[b] += 1
            if quiet[b] >= QUIET_POLLS:         # stalled: the catch-up is measured from its end
                calm[b] = 0
                self.behind[b] = True
                self.lag[b] = cycles - self.bus_tag[b]
                self.lag_polls[b] = 0
            else:
                calm[b] += 1
        if self.behind[b] and n:
            lag = cycles - self.bus_tag[b]
            if lag <= self.slack:
                self.behind[b] = False
            else:
                self.lag_polls[b] += 1
                if self.lag_polls[b] >= CATCHUP_POLLS:
                    if lag >= self.lag[b] - self.step:      # no longer shrinking: lost frames
                        self.behind[b] = False
                    self.lag[b] = lag
                    self.lag_polls[b] = 0

    def _keeps_pace(self, b: int) -> bool:
        """Bus ``b``'s trailing tags are lost frames, not a backlog still to come."""
        if self.calm[b] < CALM_POLLS:
            return False
        unread = self.peer_unread[b]
        if unread is None:
            return not self.behind[b]
        return unread() <= self.max_unread[b]

    def _re_anchor(self, cycles: int) -> None:
        d = self.div
        lb = cycles - self.slack
        asked = keeps = 0               # bit b: bus b's pace looked at (once a poll); it keeps pace
        for i in range(self.n):
            if not self.fresh_mask >> i & 1 or self.pos_sync[i] >= lb:
                continue
            b = self.bus_of[i]
            if not asked >> b & 1:
                asked |= 1 << b
                if self._keeps_pace(b):
                    keeps |= 1 << b
            if keeps >> b & 1:
                k = lb + (self.phase[i] - lb) % d
                self.pos_sync[i] = k
                if k > self.bus_tag[b]:
                    self.bus_tag[b] = k
