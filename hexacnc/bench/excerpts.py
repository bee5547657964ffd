"""CAM excerpts for ``hexacnc bench plan`` (``cam_excerpts``): line ranges of corpus programs compared with
TOPP-RA and the jerk-limited optimum, as in issue 19's table."""
from __future__ import annotations

from pathlib import Path

from ..errors import HexacncError
from .placement import PLACEMENT_NOTE, _place
from .toppra_peer import _bench_topp, _lift_feeds

#: CAM excerpts compared with the jerk-limited optimum (file, first line, last line), as in issue 19's table
CAM_EXCERPTS = (("arcspiral.ngc", 1, 200), ("tort.ngc", 25, 45), ("3D_Chips.ngc", 1, 120))


def bench_excerpts(cfg, gridpoints: int, corpus: Path, excerpts=CAM_EXCERPTS) -> dict:
    """The CAM excerpts (bench placement of the whole file, then the blocks of the line range; feeds lifted,
    dwells zeroed) against TOPP-RA and the jerk-limited optimum."""
    res = {"placement": PLACEMENT_NOTE, "feeds": "lifted for both; dwell times zeroed"}
    for name, first, last in excerpts:
        key = f"{name} lines {first}-{last}"
        f = corpus / name
        if not f.is_file():
            res[key] = {"skipped": f"no file {f}"}
            continue
        try:
            prog, _wo = _place(f.read_text(encoding="utf-8", errors="replace"), name, cfg)
            blocks = [b for b in _lift_feeds(prog.blocks) if first <= int(getattr(b, "line", 0) or 0) <= last]
            r = _bench_topp(cfg, gridpoints, blocks, f"{key} (corpus excerpt)")
        except HexacncError as exc:
            res[key] = {"planned": False, "reason": str(exc)}
            continue
        r.pop("sections", None)
        res[key] = r
    return res
