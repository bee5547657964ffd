"""``[io]``: where the program's digital I/O numbers live on the bus (M62-M66 P words).

Keys (any number of each; none: a program using I/O is refused before motion):

* ``digital_out_<P> = [drive, bit]``: output P is bit ``bit`` of drive ``drive``'s 0x60FE:1
  (physical outputs, CiA 402).  ``drive`` is the strut/drive number 1..6 of the bus layout; ``bit``
  16..31 (bits 0..15 of 0x60FE:1 are reserved by CiA 402, bit 0 is "set brake": never written);
* ``digital_in_<P> = [drive, bit]``: input P is bit ``bit`` (0..31) of drive ``drive``'s 0x60FD.

Analog outputs (M67/M68 E words) and analog inputs have no mapping yet: programs using them are
refused with the line and the channel.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

from .section import Section

MAX_CHANNEL = 1023          #: the interpreter's I/O numbers are 0..1023
OUT_BITS = (16, 31)         #: manufacturer-specific bits of 0x60FE:1
IN_BITS = (0, 31)
_KEY = re.compile(r"^(digital_out|digital_in)_(\d+)$")


@dataclass(frozen=True)
class IoConfig:
    """P number -> (drive index 0..5, bit) for digital outputs (0x60FE:1) and inputs (0x60FD)."""
    digital_out: dict = field(default_factory=dict)
    digital_in: dict = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not self.digital_out and not self.digital_in


def _pair(sec: Section, key: str, bits: tuple[int, int]) -> tuple[int, int]:
    v = sec.getvec(key, 2, minval=0)
    drive, bit = float(v[0]), float(v[1])
    if drive != int(drive) or not 1 <= drive <= 6:
        raise sec.error(key, f"drive {drive:g} must be an integer 1..6")
    if bit != int(bit) or not bits[0] <= bit <= bits[1]:
        raise sec.error(key, f"bit {bit:g} must be an integer {bits[0]}..{bits[1]}")
    return int(drive) - 1, int(bit)


def parse_io(sec: Section) -> IoConfig:
    """Read ``[io]`` (absent: empty); unknown keys are left for ``Section.finish`` to reject."""
    out: dict[int, tuple[int, int]] = {}
    inp: dict[int, tuple[int, int]] = {}
    for key in sorted(sec.table):
        m = _KEY.match(key)
        if not m:
            continue
        p = int(m.group(2))
        if p > MAX_CHANNEL:
            raise sec.error(key, f"I/O number {p} is above {MAX_CHANNEL}")
        is_out = m.group(1) == "digital_out"
        target = out if is_out else inp
        where = _pair(sec, key, OUT_BITS if is_out else IN_BITS)
        if p in target:
            raise sec.error(key, f"{m.group(1)} {p} is mapped twice")
        if where in target.values():
            raise sec.error(key, f"drive {where[0] + 1} bit {where[1]} is already used by another "
                            f"{m.group(1).replace('_', ' ')}put")
        target[p] = where
    return IoConfig(digital_out=out, digital_in=inp)
