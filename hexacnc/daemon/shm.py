"""Shared memory between the supervisor and the hot loop process.

One ``multiprocessing.shared_memory`` segment holds:

* a control/status header of int64 slots (``H_*`` indices),
* a status block of float64 slots (``S_*`` indices) guarded by a seqlock
  (``H_STATUS_SEQ`` odd while the hot loop writes),
* two fixed histograms (int64 counts, 1 microsecond bins) of cycle lateness and
  compute time, incremented by the hot loop and read by the supervisor,
* the setpoint ring: ``RING_ROWS`` rows of 8 float64
  ``[x, y, z, a, b, c (rad), line, flags]`` (platform pose, mm/rad), single
  producer (supervisor, advances ``H_RING_W``) / single consumer (hot loop,
  advances ``H_RING_R``).  Indices grow monotonically; row ``i`` lives in slot
  ``i % RING_ROWS``.  The producer writes the row before publishing the index
  (x86 stores are not reordered with other stores).

Everything is accessed through ``memoryview.cast`` views: reading or writing one
slot is a C-level copy, no Python objects besides the scalar are made.
"""
from __future__ import annotations

from multiprocessing import shared_memory

from ..setpoint import FLAG_END, ROW  # noqa: F401 (the row contract lives in hexacnc.setpoint)

# -- int64 header slots ---------------------------------------------------------------------
H_MAGIC = 0
H_RING_W = 1            #: rows written (supervisor)
H_RING_R = 2            #: rows consumed (hot loop)
H_CMD_SEQ = 3           #: supervisor increments after writing H_CMD/H_CMD_ARG
H_CMD = 4
H_CMD_ARG = 5
H_CMD_ACK = 6           #: hot loop copies H_CMD_SEQ here when done with it
H_SUP_BEAT_NS = 7       #: supervisor's monotonic ns, refreshed by its feeder thread
H_CYCLES = 8            #: cycles run
H_STATE = 9             #: hot loop state (ST_*)
H_FAULT = 10            #: fault code (F_*), 0 none
H_FAULT_STRUT = 11      #: 1-based strut / node index of the fault cause, 0 n/a
H_FAULT_ARG = 12        #: fault detail (limit code, EMCY code, ...)
H_LINE = 13             #: program line of the setpoint in use
H_OVERRUNS = 14
H_MAX_IN_ROW = 15
H_STATUS_SEQ = 16       #: seqlock over the status block
H_READY = 17            #: 1 once the loop runs with drives enabled, -1 boot failed
H_LAT_MAX_NS = 18
H_COMP_MAX_NS = 19
H_LOOP_BEAT_NS = 20     #: hot loop's monotonic ns, every cycle (watchdog)
H_PID = 21
H_PRIV_FIFO = 22        #: 1 if SCHED_FIFO was granted
H_PRIV_MLOCK = 23
H_PRIV_AFFINITY = 24    #: CPU number + 1, 0 if not pinned
H_FRAMES_TX = 25
H_FRAMES_RX = 26
H_UNDERRUNS = 27
H_END_SEEN = 28         #: rows consumed up to and including an END flag
H_EXIT = 29             #: 1 when the loop has exited cleanly, 2 when it crashed
H_STATS_CYCLES0 = 30    #: cycle count at the last statistics reset
H_EXIT_SIGNAL = 31      #: signal (SIGTERM, SIGHUP) that made the hot loop stop, disable and exit; 0 none
H_STATUSWORDS = 32      #: 6 slots: last statusword per drive
H_DRIVE_STATE = 38      #: 6 slots: 1 when the drive reports Operation Enabled
H_PHASE_SUM_NS = 44     #: N_PHASES slots: compute time per phase of the cycle, summed since the stats reset
H_PHASE_MAX_NS = 50     #: N_PHASES slots: longest time of each phase since the stats reset
H_SUP_PID = 56          #: the supervisor's pid (the hot loop stops if it is no longer its parent)
H_FAULT_NS = 57         #: monotonic ns when the fault was latched (detection latency)
H_BOOTUPS = 58          #: boot-up messages seen from the drives since the start (any state; hexacnc.daemon.reference)
H_ENCODER_ERRORS = 59   #: EMCYs with an encoder (position sensor, 0x73xx) error code since the start
H_STATUS_CYCLE = 60    #: the cycle count (H_CYCLES) of the status block's snapshot, under the seqlock
H_HOME_RESULT = 61      #: CiA 402 homing: 0 never, 1 running, 2 done, < 0 error (hexacnc.daemon.homeloop)
H_HOME_STRUT = 62       #: 1-based strut of the homing error, 0 n/a
N_PHASES = 6
PHASE_NAMES = ("poll", "supervise", "transform", "send", "feedback", "stats")
N_HEADER = 64

# -- float64 status slots -------------------------------------------------------------------
S_POSE_CMD = 0          #: 6: platform pose commanded, mm / rad
S_POSE_ACT = 6          #: 6: platform pose from feedback, mm / rad
S_STRUT_CMD = 12        #: 6: strut length commands, mm
S_STRUT_ACT = 18        #: 6: measured strut lengths, mm
S_FOLLOW = 24           #: 6: following error, mm
S_FOLLOW_MAX = 30       #: 6: max |following error| since reset, mm
S_STRUT_VEL = 36        #: 6: commanded strut velocity, mm/s
S_BUS_LOAD = 42         #: worst-case bus load of the layout (fraction of the period)
S_FK_RES = 43           #: last FK residual, mm
S_PERIOD = 44           #: configured period, s
S_FAULT_VALUE = 45      #: F_LIMIT: CycleTransform.fail_value
S_THERMAL_TGT = 46      #: 6: strut growth estimate from the supervisor's thermal observer, mm
S_THERMAL_APP = 52      #: 6: growth applied by the loop (slewed towards the target), mm
S_SPINDLE_TGT = 58      #: spindle growth target, mm
S_SPINDLE_APP = 59      #: spindle growth applied, mm
S_TRAVEL = 60           #: 6: cumulative commanded strut travel, mm (thermal model input)
S_PROBE_ARM = 66        #: touch-probe latch request (supervisor): 0 disarm, 1 contact, 2 release edge (.probelatch)
S_PROBE_REQ = 67        #: supervisor increments after writing S_PROBE_ARM
S_PROBE_ACK = 68        #: last request the hot loop took
S_PROBE_STATE = 69      #: latch state (hexacnc.daemon.probelatch OFF/ARMING/ARMED/LATCHED, < 0 error)
S_PROBE_MASK = 70       #: bit per drive whose latched position is read
S_PROBE_POS = 72        #: 6: latched drive positions at the edge, increments
S_TORQUE = 78           #: 6: drive torque actual value 0x6077, per mille of rated torque (NaN: none) (.torqueread)
S_DIN_DRIVE = 84        #: M66: drive (0..5) whose 0x60FD the supervisor asks for (hexacnc.daemon.dioread)
S_DIN_REQ = 85          #: supervisor increments after writing S_DIN_DRIVE
S_DIN_ACK = 86          #: the request the hot loop answered (S_DIN_VAL holds its value)
S_DIN_VAL = 87          #: 0x60FD of S_DIN_DRIVE as read
S_IO_OUT = 88           #: 6: program digital outputs: 0x60FE:1 word each drive acknowledged (.dioloop)
S_IO_ERR = 94           #: 0, or < 0: last digital-output write error (hexacnc.daemon.dioloop.ERROR_TEXT)
S_IO_WRITES = 95        #: digital-output writes acknowledged by the drives
S_CURRENT = 96          #: 6: drive current actual value 0x6078, per mille of rated current (NaN: none)
S_TORQUE_T = 102        #: monotonic s of the oldest of the six torque samples (NaN: not yet)
S_CURRENT_T = 103       #: monotonic s of the oldest of the six current samples (NaN: not yet)
S_TORQUE_MASK = 104     #: bit per drive with a torque value
S_CURRENT_MASK = 105    #: bit per drive with a current value
N_STATUS = 112

HIST_BINS = 4096        #: 1 us bins, last one is overflow (>= 4.095 ms)
RING_ROWS = 1 << 15     #: 16 s at 0.5 ms

# -- commands --------------------------------------------------------------------------------
CMD_NONE = 0
CMD_STOP = 1            #: controlled stop in strut space, discard queued rows, stay enabled
CMD_RESET = 2           #: clear fault: fault reset + re-enable, re-seed guards
CMD_SHUTDOWN = 3        #: controlled stop, disable drives, exit
CMD_DISABLE = 4         #: controlled stop then disable, no fault
CMD_FAULT_TEST = 5      #: raise an internal fault (tests): arg = fault code
CMD_STATS_RESET = 6     #: zero the overrun counters and maxima (the supervisor zeroes the histograms)
CMD_HOME = 9            #: CiA 402 homing of every strut (idle only; hexacnc.daemon.homeloop)

# -- hot loop states -------------------------------------------------------------------------
ST_BOOT = 0
ST_IDLE = 1             #: enabled, holding the last pose
ST_RUNNING = 2          #: consuming setpoints
ST_STOPPING = 3         #: controlled stop in progress
ST_FAULT = 4            #: drives disabled, fault latched
ST_DISABLED = 5         #: drives disabled, no fault
ST_EXITED = 6
ST_HOMING = 8           #: drives homing on their own (mode 6), targets = measured positions
STATE_NAMES = {ST_BOOT: "boot", ST_IDLE: "idle", ST_RUNNING: "running", ST_STOPPING: "stopping",
               ST_FAULT: "fault", ST_DISABLED: "disabled", ST_EXITED: "exited",
               ST_HOMING: "homing"}

# -- row flags -------------------------------------------------------------------------------

MAGIC = 0x48455841434E43  # "HEXACNC"

_OFF_HEADER = 0
_OFF_STATUS = _OFF_HEADER + 8 * N_HEADER
_OFF_HLAT = _OFF_STATUS + 8 * N_STATUS
_OFF_HCOMP = _OFF_HLAT + 8 * HIST_BINS
_OFF_RING = _OFF_HCOMP + 8 * HIST_BINS
SIZE = _OFF_RING + 8 * ROW * RING_ROWS


class Shared:
    """Views over the segment; create in the supervisor, attach by name in the hot loop."""

    def __init__(self, name: str | None = None, create: bool = False):
        if create:
            self.shm = shared_memory.SharedMemory(create=True, size=SIZE)
        else:
            self.shm = shared_memory.SharedMemory(name=name)
            # attaching registers the segment with this process's resource tracker, which would
            # unlink it when this process exits; the creator owns it
            try:
                from multiprocessing import resource_tracker
                resource_tracker.unregister(self.shm._name, "shared_memory")  # type: ignore[attr-defined]
            except Exception:
                pass
        self.owner = create
        buf = self.shm.buf
        self.h = buf[_OFF_HEADER:_OFF_STATUS].cast("q")
        self.s = buf[_OFF_STATUS:_OFF_HLAT].cast("d")
        self.hist_late = buf[_OFF_HLAT:_OFF_HCOMP].cast("q")
        self.hist_comp = buf[_OFF_HCOMP:_OFF_RING].cast("q")
        self.ring = buf[_OFF_RING:SIZE].cast("d")
        if create:
            buf[:_OFF_RING] = bytes(_OFF_RING)
            self.h[H_MAGIC] = MAGIC
        elif self.h[H_MAGIC] != MAGIC:
            raise RuntimeError(f"shared memory {name!r} is not a hexacnc segment")

    @property
    def name(self) -> str:
        return self.shm.name

    # -- supervisor side helpers (not for the hot loop) ----------------------------------
    def ring_free(self) -> int:
        return RING_ROWS - (self.h[H_RING_W] - self.h[H_RING_R])

    def ring_fill(self) -> int:
        return self.h[H_RING_W] - self.h[H_RING_R]

    def push_rows(self, rows) -> int:
        """Append rows ((N,8) float array); returns how many fitted."""
        import numpy as np
        w = self.h[H_RING_W]
        n = min(len(rows), self.ring_free())
        if n <= 0:
            return 0
        flat = np.ascontiguousarray(np.asarray(rows, dtype=np.float64)[:n]).reshape(-1)
        ring = self.ring        # memoryview slices: copied in, no numpy view of the shared buffer kept
        a = (w % RING_ROWS) * ROW
        first = min(len(flat), RING_ROWS * ROW - a)
        ring[a:a + first] = memoryview(flat[:first])
        if first < len(flat):                                       # wrapped around the end
            ring[0:len(flat) - first] = memoryview(flat[first:])
        self.h[H_RING_W] = w + n          # published after the rows are written
        return n

    def retract(self, k: int) -> bool:
        """Withdraw the queued rows from ring index ``k`` on, before the hot loop reads them.

        Lowers the write index to ``k`` (single producer: only the supervisor writes it), then checks
        that the hot loop is still short of ``k``; if it is not (it raced past: only possible when
        the caller left no margin), the index is put back and False returned.  On True the rows
        from ``k`` on are unread and the next :meth:`push_rows` overwrites them.
        """
        h = self.h
        w = h[H_RING_W]
        if not (h[H_RING_R] < k < w):
            return False
        h[H_RING_W] = k
        if h[H_RING_R] < k:
            return True
        h[H_RING_W] = w
        return False

    def command(self, code: int, arg: int = 0) -> int:
        """Post a command to the hot loop; returns its sequence number."""
        self.h[H_CMD] = code
        self.h[H_CMD_ARG] = arg
        seq = self.h[H_CMD_SEQ] + 1
        self.h[H_CMD_SEQ] = seq
        return seq

    def read_status(self) -> tuple[list[int], list[float]]:
        """Consistent copy of header and status slots (seqlock read)."""
        for _ in range(1000):
            s0 = self.h[H_STATUS_SEQ]
            if s0 & 1:
                continue
            h = self.h.tolist()
            s = self.s.tolist()
            if self.h[H_STATUS_SEQ] == s0:
                return h, s
        return self.h.tolist(), self.s.tolist()

    def close(self) -> None:
        for v in (self.h, self.s, self.hist_late, self.hist_comp, self.ring):
            v.release()
        self.shm.close()
        if self.owner:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass


def percentiles_us(hist, qs=(0.5, 0.99, 0.999)) -> list[float | None]:
    """Percentiles (microseconds, bin upper edge) from a 1 us histogram (a sequence of counts or the
    shared block's memoryview: copied, no view of it is kept)."""
    import numpy as np
    counts = np.array(hist, dtype=np.int64)
    cum = np.cumsum(counts)
    total = int(cum[-1]) if len(cum) else 0
    if total == 0:
        return [None for _ in qs]
    return [float(np.searchsorted(cum, q * total, side="left") + 1) for q in qs]
