"""Bus layout: which drive sits on which bus, and every PDO's COB-ID and mapping.

One plan is the single source of truth for the master (SDO mapping), the cyclic
codec, the bus-load calculation and the simulated drives.

Layouts (``[bus] layout``), per bus with ``k`` drives:

* ``single``: one 6-byte RPDO1 per drive, ``[0x6040 controlword u16, 0x607A target i32]``.
* ``paired``: one 8-byte RPDO1 per pair of drives carrying two int32 targets; drive A maps
  ``[0x607A, dummy 0x0007]``, drive B ``[dummy 0x0007, 0x607A]`` (each skips the other's
  bytes); both listen on COB-ID 0x200 + node id of A. An odd drive out gets a 4-byte frame.
  Controlwords travel in RPDO2 (0x300 + id, 2 bytes, asynchronous) only when they change.
* ``separate``: one 4-byte RPDO1 per drive, ``[0x607A target i32]``, controlwords as in ``paired``;
  used instead of ``paired``/``fd`` when a drive description's ``[DummyUsage]`` forbids 0x0007.
* ``fd``: one CAN FD RPDO1 per bus with all ``k`` int32 targets (24 bytes for six); drive j
  maps j leading and k-1-j trailing 32-bit dummies around 0x607A. Controlwords as in ``paired``.

Feedback, all layouts: TPDO1 (0x180 + id) = ``[0x6064 position actual i32]``, synchronous,
transmission type = ``[bus] feedback_divider``; with a divider > 1 the SYNC carries a counter
(overflow = divider) and the drives of one bus are staggered by their SYNC start value, so a
bus carries ceil(k / divider) feedback frames per cycle. TPDO2 (0x280 + id) =
``[0x6041 statusword u16]``, asynchronous on change (inhibit 1 ms + 0.2 ms/strut, event timer 1 s + 70 ms/strut).
"""
from __future__ import annotations

from dataclasses import dataclass

from .errors import BusError

#: node id of the master's heartbeat (consumed by the drives through 0x1016)
MASTER_NODE_ID = 0x7F
SYNC_COB_ID = 0x080

OBJ_CONTROLWORD = 0x6040
OBJ_STATUSWORD = 0x6041
OBJ_MODES = 0x6060
OBJ_MODES_DISPLAY = 0x6061
OBJ_POSITION_ACTUAL = 0x6064
OBJ_TARGET_POSITION = 0x607A
DUMMY_U32 = 0x0007

#: TPDO2 (statusword) inhibit time in 100 us units and event timer in ms (strut 0; staggered per strut).
#: The statusword travels on change (inhibit 1 ms); the event timer only refreshes an unchanged one, so
#: it is long: with ~1 % of the cycles carrying an asynchronous frame the bus demand's p99 stays within
#: 10 % of its median (``hexacnc bus demand``; it was 50 ms, 4 % of the cycles with the heartbeats)
STATUS_INHIBIT_100US = 10
STATUS_EVENT_TIMER_MS = 1000
#: per-strut steps: distinct periods so the drives' asynchronous frames do not keep coinciding
STATUS_EVENT_STEP_MS = 70
STATUS_INHIBIT_STEP_100US = 2
HEARTBEAT_STEP_MS = 3


def status_event_timer_ms(strut: int) -> int:
    """TPDO2 event timer of a strut: 1000, 1070, ... 1350 ms (distinct: no lasting coincidence)."""
    return STATUS_EVENT_TIMER_MS + STATUS_EVENT_STEP_MS * strut


def status_inhibit_100us(strut: int) -> int:
    """TPDO2 inhibit time of a strut (100 us units): 1.0, 1.2, ... 2.0 ms."""
    return STATUS_INHIBIT_100US + STATUS_INHIBIT_STEP_100US * strut


def heartbeat_producer_ms(heartbeat_ms: int, strut: int) -> int:
    """0x1017 of a strut: ``[bus] heartbeat_ms`` + 3 ms per strut (distinct periods)."""
    return int(heartbeat_ms) + HEARTBEAT_STEP_MS * strut
#: valid CAN FD payload lengths
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)

Mapping = tuple[tuple[int, int, int], ...]   #: ((index, subindex, bits), ...)


@dataclass(frozen=True)
class NodePlan:
    """PDO configuration of one drive. ``index`` is the strut index 0..5."""
    index: int
    node_id: int
    bus: int
    rpdo1_cob_id: int
    rpdo1_map: Mapping
    rpdo1_offset: int                 #: byte offset of this drive's target in RPDO1
    rpdo2_cob_id: int | None          #: controlword event RPDO (None: controlword is in RPDO1)
    rpdo2_map: Mapping
    tpdo1_cob_id: int
    tpdo1_map: Mapping
    tpdo1_trans_type: int             #: 1..240: every n-th SYNC
    tpdo1_sync_start: int             #: 0: no SYNC counter; else first SYNC counter value
    tpdo2_cob_id: int
    tpdo2_map: Mapping


@dataclass(frozen=True)
class CyclicFrame:
    """One RPDO1 frame sent every cycle on ``bus``; ``slots`` = ((strut index, byte offset), ...)."""
    bus: int
    cob_id: int
    length: int
    fd: bool
    slots: tuple[tuple[int, int], ...]
    has_controlword: bool             #: single layout: u16 controlword at offset-2 of each slot


@dataclass(frozen=True)
class BusPlan:
    layout: str                       #: the layout used ('separate' when dummies are not allowed)
    buses: int
    fd: bool
    feedback_divider: int
    sync_counter_overflow: int        #: 0: SYNC without counter
    bus_nodes: tuple[tuple[int, ...], ...]   #: strut indices per bus
    nodes: tuple[NodePlan, ...]
    frames: tuple[CyclicFrame, ...]
    requested_layout: str = ""        #: [bus] layout
    note: str = ""                    #: why the layout differs from the requested one

    @property
    def sync_length(self) -> int:
        return 1 if self.sync_counter_overflow else 0

    def tpdo_per_cycle(self, bus: int) -> int:
        """Worst number of TPDO1 feedback frames on ``bus`` in one cycle."""
        k = len(self.bus_nodes[bus])
        d = self.feedback_divider
        return -(-k // d)


def split_nodes(n: int, buses: int) -> tuple[tuple[int, ...], ...]:
    """Balanced contiguous split of strut indices 0..n-1 over ``buses`` buses."""
    out, start = [], 0
    for b in range(buses):
        size = n // buses + (1 if b < n % buses else 0)
        out.append(tuple(range(start, start + size)))
        start += size
    return tuple(out)


def plan_layout(bus_cfg) -> BusPlan:
    """The PDO plan of a ``[bus]`` config (:class:`hexacnc.config.BusConfig`)."""
    requested = layout = bus_cfg.layout
    note = ""
    if layout in ("paired", "fd") and not _dummies_ok(bus_cfg):
        layout = "separate"
        note = (f"[bus] layout {requested!r} needs dummy mapping (0x0007), which a drive description's "
                "[DummyUsage] does not allow: one 4-byte target RPDO per drive instead ('separate')")
    ids = tuple(int(i) for i in bus_cfg.node_ids)
    if MASTER_NODE_ID in ids:
        raise BusError(f"[bus] node_ids {list(ids)}: node id {MASTER_NODE_ID} is the master's heartbeat id")
    if layout == "fd" and not bus_cfg.fd:
        raise BusError("[bus] layout = 'fd' needs [bus] fd = true (CAN FD controller and drives)")
    if bus_cfg.buses > len(ids):
        raise BusError(f"[bus] buses = {bus_cfg.buses} exceeds the {len(ids)} drives")
    d = int(bus_cfg.feedback_divider)
    if not 1 <= d <= 240:
        raise BusError(f"[bus] feedback_divider = {d} must be 1..240 (CiA 301 transmission type)")
    overflow = d if d > 1 else 0
    groups = split_nodes(len(ids), bus_cfg.buses)
    nodes: list[NodePlan | None] = [None] * len(ids)
    frames: list[CyclicFrame] = []
    T = (OBJ_TARGET_POSITION, 0, 32)
    DU = (DUMMY_U32, 0, 32)
    for b, group in enumerate(groups):
        k = len(group)
        # RPDO1 frames and per-node mapping
        rmap: dict[int, tuple[int, Mapping, int]] = {}
        if layout == "single":
            for i in group:
                cob = 0x200 + ids[i]
                rmap[i] = (cob, ((OBJ_CONTROLWORD, 0, 16), T), 2)
                frames.append(CyclicFrame(b, cob, 6, bus_cfg.fd, ((i, 2),), True))
        elif layout == "paired":
            for p in range(0, k, 2):
                pair = group[p:p + 2]
                cob = 0x200 + ids[pair[0]]
                if len(pair) == 2:
                    rmap[pair[0]] = (cob, (T, DU), 0)
                    rmap[pair[1]] = (cob, (DU, T), 4)
                    frames.append(CyclicFrame(b, cob, 8, bus_cfg.fd, ((pair[0], 0), (pair[1], 4)), False))
                else:
                    rmap[pair[0]] = (cob, (T,), 0)
                    frames.append(CyclicFrame(b, cob, 4, bus_cfg.fd, ((pair[0], 0),), False))
        elif layout == "separate":          # no dummies: one 4-byte target frame per drive
            for i in group:
                cob = 0x200 + ids[i]
                rmap[i] = (cob, (T,), 0)
                frames.append(CyclicFrame(b, cob, 4, bus_cfg.fd, ((i, 0),), False))
        elif layout == "fd":
            cob = 0x200 + ids[group[0]]
            length = 4 * k
            if length not in FD_LENGTHS:
                raise BusError(f"[bus] layout 'fd': {k} drives on bus {b} give {length} bytes, "
                               f"not a CAN FD length {FD_LENGTHS}")
            for j, i in enumerate(group):
                rmap[i] = (cob, (DU,) * j + (T,) + (DU,) * (k - 1 - j), 4 * j)
            frames.append(CyclicFrame(b, cob, length, True, tuple((i, 4 * j) for j, i in enumerate(group)), False))
        else:
            raise BusError(f"[bus] layout {layout!r} is not one of 'single', 'paired', 'fd', 'separate'")
        for pos, i in enumerate(group):
            nid = ids[i]
            cob, mp, off = rmap[i]
            nodes[i] = NodePlan(
                index=i, node_id=nid, bus=b,
                rpdo1_cob_id=cob, rpdo1_map=mp, rpdo1_offset=off,
                rpdo2_cob_id=None if layout == "single" else 0x300 + nid,
                rpdo2_map=() if layout == "single" else ((OBJ_CONTROLWORD, 0, 16),),
                tpdo1_cob_id=0x180 + nid, tpdo1_map=((OBJ_POSITION_ACTUAL, 0, 32),),
                tpdo1_trans_type=d, tpdo1_sync_start=(pos % d) + 1 if overflow else 0,
                tpdo2_cob_id=0x280 + nid, tpdo2_map=((OBJ_STATUSWORD, 0, 16),),
            )
    return BusPlan(layout=layout, buses=bus_cfg.buses, fd=bool(bus_cfg.fd), feedback_divider=d,
                   sync_counter_overflow=overflow, bus_nodes=groups, nodes=tuple(nodes),  # type: ignore[arg-type]
                   frames=tuple(frames), requested_layout=requested, note=note)


def _dummies_ok(bus_cfg) -> bool:
    """Every node's description allows dummy 0x0007 (u32) in PDO mapping ([DummyUsage])."""
    if not hasattr(bus_cfg, "simulate"):        # a bare layout request (tests): no descriptions
        return True
    from .description import dummies_allowed
    return dummies_allowed(bus_cfg, DUMMY_U32)
