"""Probing cycle on a sphere of the reference artefact (``calib run --instrument probe``).

Five G38.2 touches through the daemon's ``probe`` op - one on top, then four around the equator
(+-x, +-y of the base frame) - each from ``clearance_mm`` outside the surface towards the centre,
retracting over the sphere between touches.  The sphere is where the *uncalibrated* machine sees
it, which may be millimetres off its nominal place (a machine at twice the synthetic tolerances:
up to 2 mm): the first touch along each axis (top, +x, +y) searches ``search_mm`` further on both
sides (it starts that much farther out and may run that much deeper), and every touch moves the
estimated centre along its direction (``contact . n - radius``), so the touch opposite (-x, -y)
and the equator's height use what the machine has seen so far.  The contact points (the
controller's tool tip at the readings latched at contact) give the sphere centre as the
controller sees it (least squares, known radius).  The machine then goes to that centre with the
usual approach and settles; its readings there are the row, and the artefact's calibrated centre
is the measured tool tip: where the controller believes the tip is at the centre, the true tip is
at the true centre (the machine's error is the same over the few mm of the cycle).  Every contact
goes to the probe log.
"""
from __future__ import annotations

import json

import numpy as np

from ..errors import DataError

#: touch directions (outward normal at the contact), top first: its height places the equator touches
DIRECTIONS = np.array([[0, 0, 1.0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
#: the first touch along each axis searches farther (the opposite one uses the centre seen so far)
SEARCH = (True, True, False, True, False)


def cycle_tip_offsets_mm(radius_mm: float, clearance_mm: float = 2.0, search_mm: float = 3.0) -> np.ndarray:
    """Tool-tip offsets from the sphere centre (mm) that bound the probing cycle's travel: the first
    touches' starts and the moves over the sphere at the safe height (for the reach checks)."""
    e = radius_mm + clearance_mm + search_mm
    up = e + 3.0
    return np.array([[e, 0, 0], [-e, 0, 0], [0, e, 0], [0, -e, 0], [0, 0, up],
                     [e, 0, up], [-e, 0, up], [0, e, up], [0, -e, up]], dtype=float)


def fit_sphere_centre(points: np.ndarray, radius: float, c0: np.ndarray) -> np.ndarray:
    """Centre of a sphere of known radius through the points (Gauss-Newton)."""
    c = np.asarray(c0, dtype=float).copy()
    for _ in range(20):
        d = points - c[None]
        n = np.linalg.norm(d, axis=1)
        r = n - radius
        J = -d / n[:, None]
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        c += step
        if np.max(np.abs(step)) < 1e-9:
            break
    return c


def _go(client, text: str, name: str) -> None:
    client.call("program", text=text, name=name, reply_timeout_s=120.0)
    st = client.call("wait", timeout_s=120.0)
    if st.get("state") != "idle":
        raise DataError(f"{name}: the machine did not come to rest ({st.get('state')}: "
                        f"{(st.get('fault') or {}).get('message', '')})")


def _words(p, abc) -> str:
    return " ".join(f"{a}{v:.6f}" for a, v in zip("XYZABC", list(p) + list(abc)))


def probe_sphere(client, centre_mm, abc_deg, radius_mm: float, clearance_mm: float = 2.0,
                 overtravel_mm: float = 2.0, feed_mm_min: float = 300.0, log_path=None,
                 search_mm: float = 3.0, lead_in=None) -> dict:
    """Touch the sphere 5 times; the centre the controller sees and the contacts.  A machine whose
    error puts the sphere up to ``clearance_mm + search_mm`` nearer or ``overtravel_mm + search_mm``
    farther than ``centre_mm`` along a touch still finds it.  ``lead_in(tip_pose)``: tool-tip poses to
    pass on the way from where the machine is to the first point over the sphere (calib run: steps
    along the straight platform line)."""
    c0 = np.asarray(centre_mm, dtype=float)
    c = c0.copy()                                 # the centre as seen so far
    safe_z = c[2] + radius_mm + clearance_mm + search_mm + 3.0
    contacts = []
    here = None                                   # retract point of the last touch
    for k, (n, wide) in enumerate(zip(DIRECTIONS, SEARCH)):
        extra = search_mm if wide else 0.0
        start = c + (radius_mm + clearance_mm + extra) * n
        end = c + (radius_mm - overtravel_mm - extra) * n
        path = [] if here is None else [here, [here[0], here[1], safe_z]]
        path += [[start[0], start[1], safe_z], start]
        pre = [] if here is not None or lead_in is None else list(lead_in(np.r_[path[0], abc_deg]))
        _go(client, "G21 G90 G94\n" + "".join(f"G53 G0 {_words(p[:3], p[3:])}\n" for p in pre)
            + "".join(f"G53 G0 {_words(p, abc_deg)}\n" for p in path) + "M2\n", f"probe approach {k + 1}")
        r = client.call("probe", tip_mm=[float(v) for v in end] + [float(v) for v in abc_deg],
                        feed_mm_min=feed_mm_min, mode="38.2", reply_timeout_s=120.0)
        contacts.append(r)
        here = start
        c = c + n * (float(np.dot(np.asarray(r["tip_pose"][:3], dtype=float) - c, n)) - radius_mm)
        if k == 0:                                # the height is known now: retract just over the sphere
            safe_z = max(c[2] + radius_mm + clearance_mm + 3.0, start[2])
        if log_path is not None:
            with open(log_path, "a", encoding="utf-8") as f:
                f.write(json.dumps({"sphere_mm": c0.tolist(), "direction": n.tolist(), "t_s": r["t_s"],
                                    "q_mm": r["q_mm"], "tip_pose": r["tip_pose"],
                                    "overtravel_mm": r["overtravel_mm"], "latched": r.get("latched", False),
                                    "q_interp_mm": r.get("q_interp_mm")}) + "\n")
    _go(client, f"G21 G90 G94\nG53 G0 {_words(here, abc_deg)}\nG53 G0 {_words([here[0], here[1], safe_z], abc_deg)}"
                f"\nM2\n", "probe retract")
    pts = np.array([r["tip_pose"][:3] for r in contacts])
    centre = fit_sphere_centre(pts, radius_mm, c)
    resid = np.linalg.norm(pts - centre[None], axis=1) - radius_mm
    return {"centre_mm": centre, "contacts": contacts, "residual_um": float(1e3 * np.sqrt(np.mean(resid ** 2)))}
