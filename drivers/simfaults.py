"""Fault specs of the simulated drives (``--fault`` / ``faults=``), see :mod:`drivers.simdrive`."""
from __future__ import annotations

from dataclasses import dataclass

from .errors import ConfigError


# --------------------------------------------------------------------------------------------
# fault specs
# --------------------------------------------------------------------------------------------
@dataclass
class FaultSpec:
    node_id: int
    kind: str             #: emcy | heartbeat | stuck | refuse
    code: int = 0x1000    #: EMCY code (kind emcy)
    delay_s: float = 0.0  #: after the drive first reaches Operation enabled

    KINDS = ("emcy", "heartbeat", "stuck", "refuse")

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """``N:emcy:0x3210@1.5``, ``N:heartbeat@2``, ``N:stuck@0.5``, ``N:refuse``."""
        body, _, delay = text.partition("@")
        parts = body.split(":")
        try:
            node = int(parts[0], 0)
            kind = parts[1]
            if kind not in cls.KINDS:
                raise ValueError(f"kind {kind!r} is not one of {', '.join(cls.KINDS)}")
            code = int(parts[2], 0) if kind == "emcy" and len(parts) > 2 else 0x1000
            if kind != "emcy" and len(parts) > 2 or len(parts) > 3:
                raise ValueError("too many ':' fields")
            d = float(delay) if delay else 0.0
            if not (0 <= d < 1e6) or not (1 <= node <= 127) or not (0 < code <= 0xFFFF):
                raise ValueError("node 1..127, code 1..0xFFFF, delay >= 0")
        except (ValueError, IndexError) as exc:
            raise ConfigError(f"--fault {text!r}: expected NODE:emcy:CODE@S, NODE:heartbeat@S, "
                              f"NODE:stuck@S or NODE:refuse ({exc})") from None
        return cls(node, kind, code, d)
