"""Unit tests of the safety chain's pieces: drive supervision, SYNC tags of position samples,
exit classification, locks, the hot process' signal flags."""
from __future__ import annotations

import os
import signal
import struct

import pytest

from hexacnc.errors import ConfigError

from drivers import cyclic, framerec
from drivers.layout import plan_layout
from hexacnc.config import load_config
from hexacnc.daemon import shm as S
from hexacnc.daemon.faults import (F_DRIVE, F_EMCY, F_FEEDBACK, F_FOLLOWING, F_HEARTBEAT, F_NMT, F_NONE,
                                   F_NOT_FOLLOWING, F_REMOTE)
from hexacnc.daemon.procs import acquire_lock, classify_exit, release_lock
from hexacnc.daemon.supervise import DriveSupervisor, following_limits_mm, history_slots
from hexacnc.errors import BusError

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

MS = 1_000_000


class FakeIO:
    def __init__(self):
        self.hb_ns = [0] * 6
        self.emcy_count = [0] * 6
        self.emcy_code = [0] * 6
        self.statusword = [0x1237] * 6
        self.nmt_state = [5] * 6
        self.pos_count = [0] * 6
        self.pos_sync = [0] * 6


def _sup(io, follow=1.0, fb_s=0.35):
    s = DriveSupervisor(io, 0.0005, [follow] * 6, 0.35, fb_s, fb_s + 0.05)
    s.fill([1000.0] * 6)
    return s


def test_history_covers_the_stall_bound():
    assert history_slots(0.0005, 0.4) >= 800
    assert history_slots(0.0005, 0.4) & (history_slots(0.0005, 0.4) - 1) == 0


def test_following_error_is_matched_to_the_sync_the_sample_answers():
    io = FakeIO()
    sup = _sup(io)
    now = 1000 * MS
    io.hb_ns = [now] * 6
    sup.arm(now)
    # a ramp: 0.1 mm per SYNC
    for k in range(1, 3001):
        sup.record(k, [1000.0 + 0.1 * k] * 6)
    act = [1000.0 + 0.1 * 2000] * 6            # exactly the command of SYNC 2000 ...
    io.pos_count = [1] * 6
    io.pos_sync[:] = [2000] * 6                   # ... answering SYNC 2000, received 1000 SYNCs later
    assert sup.check(now, act, 3000) == F_NONE
    assert max(sup.follow_now) == 0.0
    io.pos_count = [2] * 6
    io.pos_sync[:] = [2500] * 6                   # the same position said to answer SYNC 2500: 50 mm behind
    assert sup.check(now, act, 3000) == F_FOLLOWING and sup.strut == 1 and sup.arg > 49_000


def test_per_strut_limit_and_one_cycle_of_slack():
    io = FakeIO()
    sup = DriveSupervisor(io, 0.0005, [1.0, 1.0, 0.2, 1.0, 1.0, 1.0], 0.35, 0.35, 0.4)
    sup.fill([0.0] * 6)
    now = 10 * MS
    io.hb_ns = [now] * 6
    sup.arm(now)
    sup.record(10, [0.0] * 6)
    sup.record(11, [0.5] * 6)
    io.pos_count = [1] * 6
    io.pos_sync[:] = [11] * 6
    assert sup.check(now, [0.3] * 6, 11) == F_NONE      # between SYNC 10 and 11: no error
    io.pos_count = [2] * 6
    assert sup.check(now, [0.8] * 6, 11) == F_FOLLOWING and sup.strut == 3   # 0.3 mm: strut 3's 0.2


def _every_second_cycle():
    """A supervisor armed at 10 ms on a bus SYNCed every second loop cycle (a drive taking whole ms), 0.2 mm
    following limits, commands 0: (io, supervisor, now_ns)."""
    io = FakeIO()
    io.sync_every = 2
    sup = DriveSupervisor(io, 0.0005, [0.2] * 6, 0.35, 0.35, 0.4)
    sup.fill([0.0] * 6)
    now = 10 * MS
    io.hb_ns = [now] * 6
    sup.arm(now)
    return io, sup, now


def test_on_a_bus_every_second_cycle_the_slack_is_one_bus_cycle():
    """sync_every 2 (a drive taking whole ms): the drive got the commands of loop cycles 10 and 12
    only; a sample of SYNC 12 between them is no error, one beyond them is."""
    io, sup, now = _every_second_cycle()
    for k, v in ((10, 0.0), (11, 0.45), (12, 0.9)):
        sup.record(k, [v] * 6)
    io.pos_count = [1] * 6
    io.pos_sync[:] = [12] * 6
    assert sup.check(now, [0.1] * 6, 12) == F_NONE
    io.pos_count = [2] * 6
    assert sup.check(now, [1.2] * 6, 12) == F_FOLLOWING and 299 <= sup.arg <= 301


def test_on_a_bus_every_second_cycle_a_sample_older_than_the_history_is_not_checked():
    """sync_every 2: a sample whose SYNC is still in the history but whose SYNC before (k - 2) is not was
    compared with the command that overwrote that slot (k - 2 + the ring's size)."""
    io, sup, now = _every_second_cycle()
    n = sup.n_hist
    sends = 3 * n
    for k in range(1, sends + 1):
        sup.record(k, [0.0 if k <= sends - n + 1 else (100.0 if k == sends else 50.0)] * 6)
    io.pos_count = [1] * 6
    io.pos_sync[:] = [sends - n + 2] * 6           # held (50); its SYNC before, sends - n (0), no longer is:
    # its slot holds the command of SYNC sends (100), so [50, 100] would call 25 mm a 25 mm error
    assert sup.check(now, [25.0] * 6, sends) == F_NONE and max(sup.follow_now) == 0.0


@pytest.mark.parametrize("setup,code", [
    (lambda io: io.statusword.__setitem__(1, 0x0240 | 0x1000), F_DRIVE),
    (lambda io: io.statusword.__setitem__(1, 0x1037), F_REMOTE),
    (lambda io: io.statusword.__setitem__(1, 0x0237), F_NOT_FOLLOWING),
    (lambda io: io.nmt_state.__setitem__(1, 0), F_NMT),
    (lambda io: io.nmt_state.__setitem__(1, 127), F_NMT),
    (lambda io: (io.emcy_count.__setitem__(1, 1), io.emcy_code.__setitem__(1, 0x2310)), F_EMCY),
    (lambda io: io.hb_ns.__setitem__(1, 1), F_HEARTBEAT),
])
def test_each_drive_finding_names_the_drive(setup, code):
    io = FakeIO()
    sup = _sup(io)
    now = 1000 * MS
    io.hb_ns = [now] * 6
    sup.arm(now)
    assert sup.check(now, [1000.0] * 6, 0) == F_NONE
    setup(io)
    assert sup.check(now, [1000.0] * 6, 0) == code and sup.strut == 2


def test_stale_feedback_whatever_the_heartbeat():
    io = FakeIO()
    sup = _sup(io, fb_s=0.1)
    t0 = 1000 * MS
    sup.arm(t0)
    for dt_ms in (50, 99):
        io.hb_ns = [t0 + dt_ms * MS] * 6
        assert sup.check(t0 + dt_ms * MS, [1000.0] * 6, 10) == F_NONE
    io.pos_count = [1, 1, 1, 0, 1, 1]           # drive 4 sends nothing, its heartbeat lives
    io.pos_sync[:] = [5] * 6
    assert sup.check(t0 + 99 * MS, [1000.0] * 6, 10) == F_NONE
    io.hb_ns = [t0 + 102 * MS] * 6
    assert sup.check(t0 + 102 * MS, [1000.0] * 6, 10) == F_FEEDBACK and sup.strut == 4 and sup.arg >= 100


def test_following_limits_default_to_the_cycle_key(tmp_path):
    cfg = load_config(None)
    assert following_limits_mm(cfg) == [cfg.cycle.following_error_mm] * 6
    from importlib import resources
    text = (resources.files("hexacnc") / "data" / "default.toml").read_text()
    p = tmp_path / "m.toml"
    p.write_text(text.replace("[struts]\n", "[struts]\nmax_following_error_mm = [1, 1, 1, 1, 1, 0.5]\n", 1))
    assert following_limits_mm(load_config(str(p)))[5] == 0.5
    p.write_text(text.replace("[struts]\n", "[struts]\nmax_following_error_mm = -1\n", 1))
    with pytest.raises(Exception, match="max_following_error_mm"):
        load_config(str(p))
    p.write_text(text.replace("comm_loss_timeout_s = 0.2\n", "comm_loss_timeout_s = 0\n", 1))
    with pytest.raises(ConfigError, match=r"\[bus\] comm_loss_timeout_s: value 0"):
        load_config(str(p))


# -- SYNC tags in the codec -------------------------------------------------------------------
class RecBus:
    """A record bus stub: what the codec sends is dropped; ``feed`` queues frames to receive."""
    frame_records = True

    def __init__(self):
        self.rx = bytearray()
        self.out = bytearray()

    def send_records(self, view):
        return 0

    def drain_records(self, max_records=256):
        buf, self.out = self.rx, bytearray()
        self.rx = bytearray()
        self.out = buf
        return self.out, 0, len(self.out)

    def shutdown(self):
        pass

    def feed(self, cob, data):
        rec = bytearray(framerec.RECORD)
        framerec.encode(rec, 0, cob, data)
        self.rx += rec


def _codec(bus=None, unread_by_peer=None, sync_every: int = 1):
    """The default layout's codec on two record-bus stubs (``bus``: their class, default RecBus);
    ``unread_by_peer``: given to each stub before the codec is built (the drives' backlog)."""
    cfg = load_config(None)
    buses = [(bus or RecBus)(), (bus or RecBus)()]
    if unread_by_peer is not None:
        for b in buses:
            b.unread_by_peer = unread_by_peer
    io = cyclic.CyclicIO(buses, cfg.bus, batch=True, sync_every=sync_every)
    return cfg, io, buses, plan_layout(cfg.bus)


def test_samples_are_tagged_with_the_sync_they_answer_through_a_stall():
    cfg, io, buses, plan = _codec()
    d = plan.feedback_divider
    answered = []
    for k in range(1, 601):                # 600 SYNCs sent; the drives answer only the first 300 now
        io.send([0] * 6)
    for k in range(1, 301):                # the backlog arrives in one go, in SYNC order
        for nd in plan.nodes:
            if (k - nd.tpdo1_sync_start) % d == 0:
                buses[nd.bus].feed(nd.tpdo1_cob_id, struct.pack("<i", k))
                answered.append((nd.index, k))
        if k % 50 == 0:
            io.poll()
            for i in range(6):
                last = max(kk for ii, kk in answered if ii == i)
                assert io.pos_sync[i] == last == io.pos_inc[i]


class SyncCountingBus(RecBus):
    """A record bus stub that counts the SYNC frames (COB-ID 0x80) sent on it."""

    def __init__(self):
        super().__init__()
        self.syncs = 0

    def send_records(self, view):
        for p in range(0, len(view), framerec.RECORD):
            if framerec.HEADER.unpack_from(view, p)[0] == 0x80:
                self.syncs += 1
        return 0


@pytest.mark.parametrize("sync_every", [1, 2, 4])
def test_tags_count_loop_cycles_when_the_bus_runs_every_nth_cycle(sync_every):
    """A drive answers every d-th SYNC it receives (from its SYNC start value); the bus sends a SYNC
    on every ``sync_every``-th loop cycle only. Each sample carries the loop cycle of the SYNC it
    answers: its tag must be that cycle."""
    cfg, io, buses, plan = _codec(SyncCountingBus, sync_every=sync_every)
    d = plan.feedback_divider
    seen = 0
    for _ in range(2000):
        before = [b.syncs for b in buses]
        io.send([0] * 6)
        for nd in plan.nodes:
            j = buses[nd.bus].syncs
            start = nd.tpdo1_sync_start if plan.sync_counter_overflow else d
            if j != before[nd.bus] and j >= start and (j - start) % d == 0:
                buses[nd.bus].feed(nd.tpdo1_cob_id, struct.pack("<i", io.cycles))
        io.poll()
        for i in range(6):
            if io.pos_count[i]:
                assert io.pos_sync[i] == io.pos_inc[i]
                seen += 1
    assert seen > 6 * 1500


def test_tags_after_lost_frames_catch_up_once_the_bus_keeps_pace():
    cfg, io, buses, plan = _codec()
    d = plan.feedback_divider
    import random
    rnd = random.Random(3)
    worst = 0
    for k in range(1, 2001):
        io.send([0] * 6)
        for nd in plan.nodes:
            if (k - nd.tpdo1_sync_start) % d == 0 and rnd.random() >= 0.5:
                buses[nd.bus].feed(nd.tpdo1_cob_id, struct.pack("<i", k))
        io.poll()
        if k > 200:
            for i in range(6):
                worst = max(worst, io.pos_inc[i] - io.pos_sync[i]) if io.pos_count[i] else worst
    assert worst <= d        # never more than one divider period behind, never ahead
    assert all(io.pos_sync[i] <= io.pos_inc[i] + d for i in range(6))


def _stall_and_catch_up(rate, lost=0.0, stall=600, polls=3000, seed=5, peer=False):
    """One SYNC sent per poll; the drives answer promptly for 50 polls, are silent for ``stall`` polls,
    then drain their backlog at ``rate`` x the SYNC rate (a fraction ``lost`` of the answers lost);
    ``rate`` may be a function of the poll number after the stall (0: a short stall of the drives).
    Each sample carries the SYNC it answers as its position. ``peer``: the buses tell the drives'
    backlog (``unread_by_peer``: the SYNCs not yet answered, three records each). Returns, per poll
    after the stall, the worst (tag - SYNC answered) over the drives and whether the backlog was
    drained."""
    import random
    rnd = random.Random(seed)
    state = {"answered": 0, "cycles": 0}
    cfg, io, buses, plan = _codec(unread_by_peer=(lambda: 3 * (state["cycles"] - state["answered"])) if peer else None)
    d = plan.feedback_divider
    answered, credit, out = 0, 0.0, []
    for poll in range(polls):
        io.send([0] * 6)
        target = io.cycles
        if 50 <= poll < 50 + stall:
            target = answered
        elif poll >= 50 + stall:
            credit += rate(poll - 50 - stall) if callable(rate) else rate
            target = min(io.cycles, answered + int(credit))
            credit -= int(credit)
        while answered < target:
            answered += 1
            for nd in plan.nodes:
                if (answered - nd.tpdo1_sync_start) % d == 0 and rnd.random() >= lost:
                    buses[nd.bus].feed(nd.tpdo1_cob_id, struct.pack("<i", answered))
        state["answered"], state["cycles"] = answered, io.cycles
        io.poll()
        if poll >= 50 + stall:
            worst = max(io.pos_sync[i] - io.pos_inc[i] for i in range(6))
            out.append((worst, answered == io.cycles))
    return out, d


def _uneven(q: int) -> float:
    """A catch-up that stalls for 10 polls in every 30 (below the 16-poll stall mark) for its first
    1500 polls, no faster than the SYNCs on average then; 2x after that."""
    if q < 1500:
        return 0.0 if q % 30 < 10 else 1.5
    return 2.0


@pytest.mark.parametrize("rate", [2.0, 1.25, 1.1, 1.05])
def test_a_slow_catch_up_after_a_stall_keeps_each_sample_on_the_sync_it_answers(rate):
    """A drive's backlog drained barely faster than the SYNCs come (runs of one sample a poll, as a
    bus that keeps pace): every late sample is still compared with the command of its own SYNC."""
    out, d = _stall_and_catch_up(rate)
    assert max(w for w, _ in out) == 0


def test_lost_frames_in_a_catch_up_are_re_anchored_once_the_backlog_is_drained():
    from drivers.synctags import CALM_POLLS, CATCHUP_POLLS
    for peer in (False, True):
        out, d = _stall_and_catch_up(2.0, lost=0.3, peer=peer)
        assert max(w for w, _ in out) <= 0                        # never tagged newer than answered
        drained = next(k for k, (_, done) in enumerate(out) if done)
        settled = drained + 2 * CATCHUP_POLLS + CALM_POLLS
        assert settled < len(out) - 100
        assert min(w for w, _ in out[settled:]) >= -d             # then no older than one divider period


def test_a_catch_up_no_faster_than_the_syncs_for_a_while_is_not_taken_for_lost_frames():
    """Where the transport tells the drives' backlog, an uneven catch-up (short stalls of the drives
    inside it, so that the backlog does not shrink for hundreds of polls) keeps every sample on its
    own SYNC; the lag-shrink guess alone (no backlog known) takes the standing backlog for lost frames."""
    out, d = _stall_and_catch_up(_uneven, peer=True, polls=3000)
    assert max(w for w, _ in out) == 0
    assert out[-1][1]                                         # drained by the end
    guessed, _ = _stall_and_catch_up(_uneven, peer=False, polls=3000)
    assert max(w for w, _ in guessed) > 100


def test_lost_frames_with_the_backlog_known_are_re_anchored_as_soon_as_it_is_drained():
    from drivers.synctags import CALM_POLLS
    out, d = _stall_and_catch_up(_uneven, lost=0.3, peer=True, polls=3000)
    assert max(w for w, _ in out) <= 0
    drained = next(k for k, (_, done) in enumerate(out) if done)
    assert min(w for w, _ in out[drained + 2 * CALM_POLLS:]) >= -d


# -- process ends, locks ----------------------------------------------------------------------
def test_exit_classification():
    h = [0] * S.N_HEADER
    h[S.H_EXIT] = 1
    h[S.H_EXIT_SIGNAL] = signal.SIGTERM
    e = classify_exit(h, 0)
    assert e.clean and e.code == "signal" and "SIGTERM" in e.message
    h[S.H_FAULT] = 3
    assert not classify_exit(h, 0).clean
    h = [0] * S.N_HEADER
    e = classify_exit(h, -9)
    assert not e.clean and e.code == "loop_died" and "SIGKILL" in e.message


def test_lock_names_the_holder(tmp_path):
    p = str(tmp_path / "bus.lock")
    fd = acquire_lock(p, "bus socketcan can0")
    try:
        # a second open file description of the same file cannot take it
        with pytest.raises(BusError, match=rf"pid {os.getpid()}"):
            acquire_lock(p, "bus socketcan can0")
    finally:
        release_lock(fd)
    release_lock(acquire_lock(p, "bus socketcan can0"))


def test_hot_process_ignores_sigint_and_flags_sigterm():
    from hexacnc.daemon import loop
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1)}
    try:
        loop.SIGNALS[:] = [0, 0]
        loop.install_signal_handlers(signal.SIGUSR1)
        os.kill(os.getpid(), signal.SIGINT)          # ignored: no KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGHUP)
        assert loop.SIGNALS[0] == signal.SIGHUP
        os.kill(os.getpid(), signal.SIGUSR1)
        assert loop.SIGNALS[1] == 1
    finally:
        loop.SIGNALS[:] = [0, 0]
        for s, h in old.items():
            signal.signal(s, h)


def test_a_stopped_process_is_told_from_a_starved_one():
    import subprocess
    import sys
    import time
    from hexacnc.daemon.procs import process_state
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        os.kill(p.pid, signal.SIGSTOP)
        for _ in range(100):
            if process_state(p.pid) == "T":
                break
            time.sleep(0.01)
        assert process_state(p.pid) == "T"
        os.kill(p.pid, signal.SIGCONT)
        time.sleep(0.05)
        assert process_state(p.pid) in ("S", "R")
    finally:
        p.kill()
        p.wait()
    assert process_state(p.pid) == ""
