"""Placement of corpus programs in the workspace for the planner benches (``hexacnc bench plan``)."""
from __future__ import annotations

import numpy as np

#: how the bench places a corpus program (the ``placement`` value in the bench's JSON)
PLACEMENT_NOTE = "G54 origin = home tool-tip position minus the program's bounding-box centre; no scaling"


def _place(text: str, name: str, cfg):
    """Interpret once at G54 = 0 to find the bounding box, then again with the centring work offset."""
    from ..gcode.factory import machine_defaults, program_from_config
    home = np.asarray(cfg.home_pose, dtype=float)
    zero = [0.0, 0.0, 0.0] + [float(v) for v in home[3:]]
    prog = program_from_config(text, name, cfg, work_offsets={1: zero})
    E = np.array([b.end for b in prog.blocks if getattr(b, "end", None) is not None])
    if E.size == 0:
        return prog, [0.0, 0.0, 0.0]
    ctr = 0.5 * (E[:, :3].min(axis=0) + E[:, :3].max(axis=0))
    tip_home = np.asarray(machine_defaults(cfg)["start_pose"][:3])      # the tool tip at the home pose
    off = tip_home - ctr
    wo = [float(v) for v in off] + [float(v) for v in home[3:]]
    return program_from_config(text, name, cfg, work_offsets={1: wo}), wo[:3]
