"""The time-optimal jerk-limited stop of one axis, one cycle at a time (plain floats): used by the
hot loop's controlled stop (``hexacnc.daemon.stopgen``), the playback rate of a setpoint source and
the simulated drives' own stop ramps (``drivers.simreact``)."""
from __future__ import annotations

import math

#: share of the strut acceleration and jerk limits a controlled stop is planned at (the master also
#: commissions the drives' quick-stop deceleration 0x6085 and profile jerk 0x60A4:1 at this share)
STOP_SHARE = 0.9


def stop_accel(v: float, a: float, jmax: float, amax: float, dt: float) -> float:
    """Acceleration (mm/s^2) for the next cycle of a jerk-limited stop from ``(v, a)``.

    Discrete model (the one the drive and the guard see): ``v`` and ``a`` are
    backward differences of the commanded lengths; the next acceleration ``x``
    gives ``v' = v + x dt``; ramping ``x`` back to zero in steps of ``jmax dt``
    then adds ``x|x|/(2 jmax) - x dt/2``.  ``x`` solves ``v + x dt/2 + x|x|/(2 jmax) = 0``
    and is clamped to the jerk and acceleration bounds (an ``a`` beyond ``amax`` is only brought
    back towards it at ``jmax``, never stepped).
    """
    jdt = jmax * dt
    lo = a - jdt
    hi = a + jdt
    if lo < -amax:
        lo = -amax if a >= -amax else a
    if hi > amax:
        hi = amax if a <= amax else a
    xs = -v / dt                      # reach standstill in this very cycle?
    if lo <= xs <= hi and -jdt <= xs <= jdt:
        return xs
    h = 0.5 * dt
    if v <= 0.0:
        x = jmax * (-h + math.sqrt(h * h - 2.0 * v / jmax))
    else:
        x = jmax * (h - math.sqrt(h * h + 2.0 * v / jmax))
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x
