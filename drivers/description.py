"""Drive descriptions (EDS / DCF) per node: what a drive must report, and what it allows.

``[bus] nodes`` may name one EDS or DCF per node (``BusConfig.node_eds``, "" = the bundled default);
the bundled default is ``hexapod_drive.eds``, or ``strict_drive.eds`` when the simulated drives run
the ``strict`` profile (``[bus] simulate = true``, ``[bus] simulate_profile = "strict"``).

From a description this module takes (plain values, cached per file):

* the identity the drive must report in 0x1018 (``[DeviceInfo]`` VendorNumber, ProductNumber,
  RevisionNumber; a number 0 in the description is not checked), the device type 0x1000
  (its DefaultValue) and the supported modes 0x6502 (its DefaultValue, CSP bit 7 required);
* ``[DummyUsage]``: which dummy objects (0x0001..0x0007) RPDO mapping may use;
* the 0x60C2 sub 2 interpolation time index range (LowLimit..HighLimit, default -6..-3);
* which objects exist (optional objects such as 0x1029, 0x6007, 0x605C, the factor group).
"""
from __future__ import annotations

import configparser
import functools
import os
from dataclasses import dataclass
from pathlib import Path

import canopen

from .errors import BusError

DRIVERS_DIR = Path(__file__).resolve().parent
DEFAULT_EDS = DRIVERS_DIR / "hexapod_drive.eds"
STRICT_EDS = DRIVERS_DIR / "strict_drive.eds"
PROFILES = ("permissive", "strict")

#: CiA 402 device type: profile 402 in bits 0..15; bits 16..23 "servo drive" (0x02)
DEVICE_TYPE_CIA402 = 402
#: 0x6502 bit of cyclic synchronous position mode (mode 8)
MODES_CSP_BIT = 1 << 7
MODE_BITS = {0: "pp", 1: "vl", 2: "pv", 3: "tq", 5: "hm", 6: "ip", 7: "csp", 8: "csv", 9: "cst"}
#: 0x60C2 index range when the description gives no limits
IP_INDEX_RANGE = (-6, -3)


#: manufacturer objects of the bundled descriptions the master configures (by index and exact name)
BUNDLED_OBJECTS = {0x2010: "SYNC loss time-out ms", 0x2110: "Holding brake"}


@dataclass(frozen=True)
class Description:
    path: str
    vendor_id: int            #: 0: not checked
    product_code: int         #: 0: not checked
    revision: int             #: 0: not checked
    device_type: int
    supported_modes: int
    dummies: frozenset        #: dummy indices (1..7) allowed in PDO mapping
    ip_index_range: tuple     #: (low, high) of 0x60C2 sub 2
    objects: frozenset        #: object indices present
    product_name: str
    #: manufacturer objects of the bundled EDS present under their name (another vendor's 0x2010 is
    #: something else): {index: name}, e.g. 0x2010 "SYNC loss time-out ms", 0x2110 "Holding brake"
    bundled: tuple = ()

    def has_bundled(self, index: int) -> bool:
        return index in dict(self.bundled)

    def has(self, index: int) -> bool:
        return index in self.objects


def modes_text(bits: int) -> str:
    return ",".join(name for b, name in MODE_BITS.items() if bits >> b & 1) or "none"


def _dummy_usage(path: str) -> frozenset:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str
    with open(path, encoding="latin-1") as f:
        cp.read_file(f)
    out = set()
    if cp.has_section("DummyUsage"):
        for key, value in cp.items("DummyUsage"):
            try:
                if key.lower().startswith("dummy") and int(value.strip() or "0", 0):
                    out.add(int(key[5:], 16))
            except ValueError:
                raise BusError(f"{path}: [DummyUsage] {key} = {value!r} is not 0 or 1") from None
    return frozenset(out)


@functools.lru_cache(maxsize=32)
def load_description(path: str) -> Description:
    """Parse an EDS/DCF (cached). Raises :class:`BusError` naming the file and what is missing."""
    if not os.path.isfile(path):
        raise BusError(f"drive description {path}: no such file")
    try:
        od = canopen.import_od(path)
    except Exception as exc:       # canopen raises many kinds on a bad file
        raise BusError(f"drive description {path}: cannot be read as EDS/DCF: {exc}") from exc
    for index, what in ((0x1000, "device type"), (0x1018, "identity"), (0x6502, "supported drive modes"),
                        (0x60C2, "interpolation time period")):
        if index not in od:
            raise BusError(f"drive description {path}: object 0x{index:04X} ({what}) is missing")
    di = od.device_information
    ip = od[0x60C2]
    try:
        sub2 = ip[2]
    except KeyError:
        raise BusError(f"drive description {path}: object 0x60C2 has no sub-index 2 (index)") from None
    lo = sub2.min if sub2.min is not None else IP_INDEX_RANGE[0]
    hi = sub2.max if sub2.max is not None else IP_INDEX_RANGE[1]
    objects = frozenset(int(i) for i in od.indices)
    bundled = tuple((i, n) for i, n in BUNDLED_OBJECTS.items() if i in od and od[i].name == n)
    return Description(
        path=path, vendor_id=int(di.vendor_number or 0), product_code=int(di.product_number or 0),
        revision=int(di.revision_number or 0), device_type=int(od[0x1000].default or 0),
        supported_modes=int(od[0x6502].default or 0), dummies=_dummy_usage(path),
        ip_index_range=(int(lo), int(hi)), objects=objects, product_name=str(di.product_name or ""),
        bundled=bundled)


def default_path(bus_cfg) -> str:
    """The bundled description for nodes without their own (per ``[bus] simulate_profile``)."""
    strict = getattr(bus_cfg, "simulate", False) and getattr(bus_cfg, "simulate_profile", "permissive") == "strict"
    return str(STRICT_EDS if strict else DEFAULT_EDS)


def node_paths(bus_cfg) -> list[str]:
    """Description file per node, in ``[bus] node_ids`` order."""
    named = tuple(getattr(bus_cfg, "node_eds", ()) or ())
    dflt = default_path(bus_cfg)
    return [(named[i] if i < len(named) and named[i] else dflt) for i in range(len(bus_cfg.node_ids))]


def node_descriptions(bus_cfg) -> list[Description]:
    return [load_description(p) for p in node_paths(bus_cfg)]


def dummies_allowed(bus_cfg, index: int = 0x0007) -> bool:
    """True when every node's description allows dummy ``index`` in its PDO mapping."""
    return all(index in d.dummies for d in node_descriptions(bus_cfg))


def expected_identity(bus_cfg, strut: int, desc: Description) -> tuple[int, int, int]:
    """(vendor, product, revision) expected from node ``strut``: the config's ``[bus] nodes`` entry
    where it names them (-1 = not named), else the description's (0 = not checked)."""
    cfg_ids = tuple(getattr(bus_cfg, "node_identity", ()) or ())
    want = [desc.vendor_id, desc.product_code, desc.revision]
    if strut < len(cfg_ids):
        for k, v in enumerate(cfg_ids[strut]):
            if v >= 0:
                want[k] = v
    return want[0], want[1], want[2]


def identity_problems(found: dict, want_identity: tuple[int, int, int], desc: Description) -> list[str]:
    """Differences between what a node reported (``found``: keys device_type, vendor_id, product_code,
    revision, supported_modes) and what is expected: one text per object, naming expected and found."""
    out = []
    dt = found.get("device_type")
    if dt is not None:
        if dt & 0xFFFF != DEVICE_TYPE_CIA402:
            out.append(f"0x1000 device type: expected a CiA 402 drive (0x....0192), found 0x{dt:08X}")
        elif desc.device_type and dt != desc.device_type:
            out.append(f"0x1000 device type: expected 0x{desc.device_type:08X} ({desc.path}), found 0x{dt:08X}")
    for sub, key, name, want in ((1, "vendor_id", "vendor-ID", want_identity[0]),
                                 (2, "product_code", "product code", want_identity[1]),
                                 (3, "revision", "revision number", want_identity[2])):
        got = found.get(key)
        if got is not None and want and got != want:
            out.append(f"0x1018:{sub:02d} {name}: expected 0x{want:08X}, found 0x{got:08X}")
    modes = found.get("supported_modes")
    if modes is not None and not modes & MODES_CSP_BIT:
        out.append(f"0x6502 supported drive modes: expected cyclic synchronous position (bit 7), "
                   f"found 0x{modes:08X} ({modes_text(modes)})")
    return out


def interpolation_candidates(period_s: float, index_range: tuple[int, int] = (-6, -3),
                             max_multiple: int = 20) -> list[tuple[int, int, float]]:
    """(value, index, bus period s) that 0x60C2 can express for whole multiples of ``period_s`` up to
    ``max_multiple``: shortest bus period first, then coarsest index first (-3, whole ms, is the most
    widely accepted). BusError when there is none."""
    lo, hi = index_range
    out = []
    for mult in range(1, max_multiple + 1):
        p = period_s * mult
        for idx in range(min(hi, 0), max(lo, -9) - 1, -1):
            v = p / 10.0 ** idx
            if abs(v - round(v)) < 1e-6 * max(1.0, v) and 1 <= round(v) <= 255:
                out.append((int(round(v)), idx, p))
    if not out:
        raise BusError(f"[cycle] period_s = {period_s:g} s: no multiple up to x{max_multiple} can be written as "
                       f"0x60C2 value (1..255) x 10^index with index {lo}..{hi}")
    return out


def common_index_range(bus_cfg) -> tuple[int, int]:
    """0x60C2 index range every node's description allows."""
    descs = node_descriptions(bus_cfg)
    return max(d.ip_index_range[0] for d in descs), min(d.ip_index_range[1] for d in descs)


def bus_period_s(bus_cfg, period_s: float) -> float:
    """The bus (SYNC) period the master will first try for a loop period: ``period_s`` when 0x60C2
    can express it in the descriptions' index range, else the shortest multiple that it can
    (e.g. 1 ms for 0.5 ms with drives that take only index -3)."""
    if not hasattr(bus_cfg, "simulate"):       # a bare layout request (tests): no descriptions
        return period_s
    lo, hi = common_index_range(bus_cfg)
    if lo > hi:
        raise BusError(f"the drive descriptions allow no common 0x60C2 index ({node_paths(bus_cfg)})")
    return interpolation_candidates(period_s, (lo, hi))[0][2]
