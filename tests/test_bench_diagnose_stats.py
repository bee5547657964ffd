"""``hexacnc bench diagnose``: the parameter-error statistics of its rows (z = error / standard error)."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.bench import diagnose as B

pytestmark = pytest.mark.unit


def _row(zs, **kw):
    zs = list(zs)
    r = {"scenario": "x", "seed": 1, "data": "full_pose", "expect_inseparable": False, "named_exactly": True,
         "named_or_reported_inseparable": True, "extra": [], "missing": [], "inseparable": [], "verdict": "x",
         "meets_rms": True, "holdout_rms_over_noise_floor": 1.0,
         "parameter_z_rms": float(np.sqrt(np.mean(np.square(zs)))), "parameter_count": len(zs),
         "parameter_chi2_p": B._chi2_p(zs), "meets_parameter_errors": bool(np.sqrt(np.mean(np.square(zs))) <= 1.5)}
    r.update(kw)
    return r


def test_honest_standard_errors_pass_the_pooled_check_and_the_chi_square_flags_small_ones():
    rng = np.random.default_rng(20261128)     # fixed: the bounds below are ~4 sigma, not certain
    honest = [_row(rng.standard_normal(int(rng.integers(1, 13)))) for _ in range(300)]
    s = B.summary(honest)["full_pose"]
    assert 0.85 <= s["parameter_z_rms_pooled"] <= 1.15
    # about 1 % of honest rows fall below chi-square p 0.01; the 1.5 bound alone fails more often
    assert s["parameter_chi2_p_below_0p01"] <= 12
    assert len(s["parameter_errors_failing"]) == s["parameter_errors_checked"] - s["meets_parameter_errors_z_rms_1p5"]
    # standard errors 2x too small: pooled z ~2 and most rows flagged
    small = [_row(2.0 * rng.standard_normal(6)) for _ in range(100)]
    s2 = B.summary(small)["full_pose"]
    assert s2["parameter_z_rms_pooled"] > 1.6
    assert s2["parameter_chi2_p_below_0p01"] > 45      # P(4 chi2_6 > chi2_6(0.99)) = 0.65: ~65 of 100, sd ~5
    assert B._chi2_p([]) is None and B._pooled_z([]) is None
