"""The controlled stop's profile (``hexacnc.daemon.stopgen``): every single-cycle difference of the
generated commands within the limits, and within the planned share of them, from many initial states."""
import numpy as np
import pytest

from hexacnc.daemon.stopgen import STOP_SHARE, StrutStop, peak_speed

DT = 0.0005
VMAX, AMAX, JMAX = 500.0, 5000.0, 2e5
LMIN, LMAX = 700.0, 1350.0


def _states(rng, n):
    """(v, a) per strut: at the limits, near zero, opposite and equal signs, above the share."""
    kind = rng.integers(0, 6, n)
    v = rng.uniform(-VMAX, VMAX, n)
    a = rng.uniform(-AMAX, AMAX, n)
    sv, sa = rng.choice([-1.0, 1.0], n), rng.choice([-1.0, 1.0], n)
    v = np.where(kind == 0, sv * VMAX, v)                                  # at the velocity limit
    a = np.where(kind == 0, -sv * rng.uniform(0, AMAX, n), a)             # (decelerating or not)
    a = np.where(kind == 1, sa * AMAX, a)                                  # at the acceleration limit
    v = np.where(kind == 2, rng.uniform(-1e-3, 1e-3, n), v)                # near zero
    a = np.where(kind == 2, rng.uniform(-1.0, 1.0, n), a)
    a = np.where(kind == 3, -np.sign(v) * np.abs(a), a)                   # opposite signs
    a = np.where(kind == 4, np.sign(v) * np.abs(a), a)                    # same signs
    a = np.where(kind == 5, sa * rng.uniform(STOP_SHARE, 1.0, n) * AMAX, a)  # above the share
    # feasible: the motion so far could still be brought to rest within the velocity limit
    v = np.clip(v, -VMAX, VMAX)
    over = np.abs(v + a * np.abs(a) / (2 * JMAX)) > VMAX
    return np.where(over, np.sign(v) * (VMAX - a * a / (2 * JMAX)), v), a


def _stop(v, a, l0=None):
    st = StrutStop([VMAX] * 6, [AMAX] * 6, [JMAX] * 6, [LMIN] * 6, [LMAX] * 6, DT)
    l0 = np.full(6, 1000.0) if l0 is None else l0
    l1 = l0 - v * DT
    l2 = l1 - (v - a * DT) * DT
    st.start(l0, l1, l2)
    hist = [l2, l1, l0]
    out = [0.0] * 6
    for _ in range(20000):
        if not st.step(out):
            break
        hist.append(np.array(out))
    else:
        raise AssertionError("the stop did not end")
    hist += [np.array(out)] * 3
    H = np.array(hist)
    V = np.diff(H, axis=0) / DT
    A = np.diff(V, axis=0) / DT
    J = np.diff(A, axis=0) / DT
    return H, V, A, J


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_stop_stays_within_the_limits_and_its_share_from_random_states(seed):
    rng = np.random.default_rng(seed)
    for _ in range(150):
        v, a = _states(rng, 6)
        H, V, A, J = _stop(v, a)
        tol = 1e-6
        V = V[1:]                                   # V[0]: the (given) cycle before the start
        assert np.all(np.abs(V) <= VMAX * (1 + tol))
        a_cap = np.maximum(STOP_SHARE * AMAX, np.abs(a))              # a start above the share only falls
        assert np.all(np.abs(A) <= a_cap * (1 + tol) + 1e-3)
        assert np.all(np.abs(A) <= AMAX * (1 + tol))
        # jerk: the share, except a strut whose velocity would overshoot VMAX at the share (full limit)
        near_vmax = np.array([v[i] * a[i] > 0 and peak_speed(v[i], a[i], STOP_SHARE * JMAX, DT) > VMAX
                              for i in range(6)])
        j_cap = np.where(near_vmax, JMAX, STOP_SHARE * JMAX)
        assert np.all(np.abs(J) <= j_cap * (1 + tol) + 1e-3), (v, a, np.abs(J).max(axis=0))
        assert np.all(V[-2:] == 0.0)                                   # at rest
        assert np.all((H >= LMIN) & (H <= LMAX))


def test_most_states_stop_at_the_share_not_the_full_limit():
    """The fallback to the full jerk is rare: it only serves states accelerating near VMAX."""
    rng = np.random.default_rng(11)
    near = 0
    for _ in range(200):
        v, a = rng.uniform(-300, 300, 6), rng.uniform(-AMAX, AMAX, 6)
        near += sum(v[i] * a[i] > 0 and peak_speed(v[i], a[i], STOP_SHARE * JMAX, DT) > VMAX for i in range(6))
        _, _, _, J = _stop(v, a)
        assert np.abs(J).max() <= STOP_SHARE * JMAX * (1 + 1e-6)
    assert near == 0


def test_stop_is_close_to_time_optimal_at_the_share():
    """No margin taken twice: the stop ends within the time-optimal bound at the shared limits."""
    for v0, a0 in [(400.0, 0.0), (-250.0, 3000.0), (150.0, 4000.0), (0.5, -20.0)]:
        H, V, A, J = _stop(np.full(6, v0), np.full(6, a0))
        am, jm = STOP_SHARE * AMAX, STOP_SHARE * JMAX
        bound = (abs(v0) + a0 * a0 / (2 * jm)) / am + 2 * am / jm + 0.005
        assert (len(H) - 6) * DT <= bound


def test_peak_speed_matches_the_ramp_down():
    v, a, j = 100.0, 4000.0, STOP_SHARE * JMAX
    vv, aa = v, a
    top = v
    while aa > 0:
        aa = max(0.0, aa - j * DT)
        vv += aa * DT
        top = max(top, vv)
    assert peak_speed(v, a, j, DT) == pytest.approx(top, rel=1e-9)
    assert peak_speed(-v, -a, j, DT) == pytest.approx(top, rel=1e-9)


# -- the bench's estimate of the peaks from targets rounded to drive increments ----------------
INC_MM = 1e-4


def _random_stop_stream(rng):
    v, a = rng.uniform(-300, 300, 6), rng.uniform(-4000, 4000, 6)
    t = np.arange(40)[:, None] * DT
    pre = 800.0 + rng.uniform(0, 1, 6) + v * t + 0.5 * a * t * t      # constant acceleration before
    st = StrutStop([VMAX] * 6, [AMAX] * 6, [JMAX] * 6, [LMIN] * 6, [LMAX] * 6, DT)
    st.start(pre[-1], pre[-2], pre[-3])
    rows, out = [], [0.0] * 6
    while st.step(out):
        rows.append(list(out))
    return np.vstack([pre, np.array(rows), np.array([out] * 40)])


def test_peak_estimate_of_rounded_stops_stays_within_share_plus_resolution():
    from hexacnc.bench.ringtap import motion_peaks, peak_estimator
    est = peak_estimator(DT, INC_MM, VMAX, AMAX, JMAX)
    assert max(est.resolution.values()) <= 0.02
    rng = np.random.default_rng(5)
    worst = 0.0
    for _ in range(100):
        L = _random_stop_stream(rng)
        exact = motion_peaks(L, DT, VMAX, AMAX, JMAX, INC_MM)
        rounded = motion_peaks(np.round(L / INC_MM) * INC_MM, DT, VMAX, AMAX, JMAX, INC_MM)
        assert exact["j"] <= STOP_SHARE * (1 + 1e-6)
        for k in "vaj":
            assert abs(rounded[k] - exact[k]) <= est.resolution[k] * (1 + 1e-9) + 1e-12
        worst = max(worst, rounded["j"])
    assert STOP_SHARE - 0.05 < worst < 1.0      # the stops reach their jerk share, measured below 1.0


def test_peak_estimate_sees_a_real_excess():
    """A stream whose jerk is 1.1x the limit for 25 ms reads over 1.0 despite the window."""
    from hexacnc.bench.ringtap import motion_peaks
    n = 50
    j = np.zeros(200)
    j[20:20 + n] = 1.1 * JMAX
    j[20 + n:20 + 2 * n] = -1.1 * JMAX
    a = np.cumsum(j) * DT
    v = np.cumsum(a) * DT
    L = 1000.0 + np.cumsum(v) * DT
    pk = motion_peaks(np.round(np.repeat(L[:, None], 6, axis=1) / INC_MM) * INC_MM, DT, VMAX, AMAX, JMAX, INC_MM)
    assert pk["j"] > 1.05


# -- the simulated drives' own quick stop (0x6085 at the profile jerk 0x60A4:1) ----------------
def _ramp_demands(v, a, decel, jerk):
    from drivers.simreact import Ramp
    r = Ramp(1000.0, v, decel, None, jerk, a)
    xs = [1000.0 - 2 * v * DT + a * DT * DT, 1000.0 - v * DT, 1000.0]   # the demands before: v, a
    for _ in range(20000):
        if r.done:
            break
        xs.append(r.step(DT))
    else:
        raise AssertionError("the ramp did not end")
    xs += [xs[-1]] * 3
    X = np.array(xs)
    return np.diff(X) / DT, np.diff(X, 2) / DT ** 2, np.diff(X, 3) / DT ** 3


def test_drive_quick_stop_ramp_is_jerk_limited_from_the_demand_it_had():
    rng = np.random.default_rng(3)
    decel, jerk = STOP_SHARE * AMAX, STOP_SHARE * JMAX
    for _ in range(200):
        v, a = rng.uniform(-400, 400), rng.uniform(-decel, decel)
        if v * a > 0 and peak_speed(v, a, jerk, DT) > VMAX:
            continue
        V, A, J = _ramp_demands(v, a, decel, jerk)
        assert np.abs(J).max() <= jerk * (1 + 1e-6) + 1e-3, (v, a, np.abs(J).max())
        assert np.abs(A[1:]).max() <= decel * (1 + 1e-6) + 1e-3
        assert np.all(V[-2:] == 0.0)


def test_drive_quick_stop_without_profile_jerk_is_the_0x6085_trapezoid():
    V, A, J = _ramp_demands(50.0, 0.0, 1000.0, 0.0)
    assert np.abs(A[1:]).max() == pytest.approx(1000.0, rel=1e-6)
    assert (len(V) - 4) * DT == pytest.approx(50.0 / 1000.0, abs=2 * DT)
