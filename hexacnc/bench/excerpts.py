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


def bench_optimum_only(cfg, corpus: Path | None, at_shares: bool = False, only=None, by_terms: bool = False) -> dict:
    """hexacnc against the jerk-limited optimum alone (no TOPP-RA) on the bench paths and the CAM excerpts:
    per path the plan's duration and measured utilisation, the optimum's keys (feeds lifted, dwells zeroed).
    ``at_shares``: also the optimum at the planner's shares; ``by_terms``: also the optimum with the jerk terms
    bounded one by one; ``only``: path names (keys' first word) to run."""
    import time
    from ..planner import plan_program
    from .jerkfloor import _rest_points
    from .jerkopt import jerk_optimum_report
    from .planloss import time_loss
    from .toppra_peer import _lifted_config, smooth_path_blocks, stops_path_blocks, topp_path_blocks
    cfg = _lifted_config(cfg, False)
    paths = {"corners": topp_path_blocks(cfg), "smooth": smooth_path_blocks(cfg), "stops": stops_path_blocks(cfg)}
    for name, first, last in CAM_EXCERPTS:
        f = None if corpus is None else corpus / name
        if f is not None and f.is_file():
            prog, _wo = _place(f.read_text(encoding="utf-8", errors="replace"), name, cfg)
            paths[f"{name} lines {first}-{last}"] = [b for b in _lift_feeds(prog.blocks)
                                                     if first <= int(getattr(b, "line", 0) or 0) <= last]
    out = {}
    for key, blocks in paths.items():
        if only and key.split(" ")[0].split(".")[0] not in only:
            continue
        t0 = time.perf_counter()
        try:
            plan = plan_program(blocks, cfg)
        except HexacncError as exc:
            out[key] = {"planned": False, "reason": str(exc)}
            continue
        t_plan = time.perf_counter() - t0
        jo = jerk_optimum_report(plan, cfg, _rest_points(plan), at_shares=at_shares, by_terms=by_terms)
        out[key] = {"hexacnc_duration_s": round(plan.duration_s, 6),
                    "hexacnc_utilisation": {k: round(v, 6) for k, v in plan.utilisation.items()},
                    "utilisation_ok": bool(max(plan.utilisation.values()) <= 1.0),
                    "hexacnc_planning_s": round(t_plan, 4),
                    "jerk_optimum_s": jo.get("jerk_optimum_s"), "jerk_optimum_ratio": jo.get("jerk_optimum_ratio"),
                    "jerk_optimum_utilisation": jo.get("utilisation"), "jerk_optimum": jo}
        out[key]["time_loss"] = time_loss(blocks, cfg)
        if at_shares:
            out[key]["jerk_optimum_at_shares_ratio"] = jo.get("jerk_optimum_at_shares_ratio")
        if by_terms:
            out[key]["jerk_optimum_by_terms_ratio"] = jo.get("jerk_optimum_by_terms_ratio")
        if at_shares and by_terms:
            for k in ("jerk_optimum_by_terms_at_shares_ratio", "by_terms_at_shares_cost"):
                out[key][k] = jo.get(k)
    return out
