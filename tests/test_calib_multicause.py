"""Several hidden causes, per-strut causes, partial data: found, or reported inseparable (issue 17).

Seeds are drawn at test time (os.urandom) and printed on failure; the exhaustive
matrix (every single cause and pair, full-pose and positions-only) is
``hexacnc bench diagnose``.
"""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from hexacnc.calib import synth
from hexacnc.calib.diagnose import Options, diagnose
from hexacnc.config import load_config


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def fresh_seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


def labels(res: dict) -> list[str]:
    return sorted(c["name"] + ("_per_strut" if c["form"] == "per_strut" else "") for c in res["causes"])


def floor_mm(s, measured: str) -> float:
    return s.noise_mm * math.sqrt(sum(ch in measured for ch in "xyz"))


def run(cfg, effects, seed, measured="xyzabc", n_fit=100, n_hold=50):
    s = synth.generate(cfg, seed, effects=tuple(effects), n_fit=n_fit, n_holdout=n_hold, measure_set=measured)
    d = diagnose(cfg, s.fit, s.holdout, Options(noise_mm=s.noise_mm, noise_deg=s.noise_deg, frame="base"))
    return s, d.result


def test_a_pair_of_causes_is_named_with_own_gains(cfg):
    import itertools

    from hexacnc.calib.model import base_cause
    rng = np.random.default_rng(fresh_seed())
    pairs = [p for p in itertools.combinations(synth.EFFECTS, 2) if base_cause(p[0]) != base_cause(p[1])]
    effects = pairs[rng.integers(len(pairs))]
    measured = ("xyzabc", "xyz")[rng.integers(2)]
    seed = int(rng.integers(2 ** 31))
    s, r = run(cfg, effects, seed, measured)
    msg = f"hidden {effects} ({measured}) seed {seed}: verdict {r['verdict']}"
    assert labels(r) == sorted(effects), msg
    assert "none" not in r["verdict"] and not r["inseparable_causes"], msg
    assert r["extended"]["rms_holdout"]["position_mm"] <= 1.5 * floor_mm(s, measured), msg
    for c in r["causes"]:   # each cause earns its place next to the other, on the held-out set too
        ev = c["evidence"]
        assert ev["cv_gain_in_presence_of_others"] > 1.03 and ev["holdout_gain"] > 1.1, (msg, c["name"], ev)
        assert all(v > 0 for v in c["parameter_std"].values()), msg


def test_per_strut_compliance_is_chosen_over_the_common_one(cfg):
    seed = fresh_seed()
    s, r = run(cfg, ["elastic_sag_per_strut"], seed)
    msg = f"seed {seed}: verdict {r['verdict']}"
    assert labels(r) == ["elastic_sag_per_strut"], msg
    c = r["causes"][0]
    v = c["variant"]
    assert v["chosen"] == "per_strut" and v["cv_gain_per_strut_over_common"] > 1.03, (msg, v)
    assert v["delta_bic_per_strut_minus_common"] < -10, (msg, v)
    true = np.array([s.effects_params["elastic_sag_per_strut"][f"compliance{i}_mm_per_kN"] for i in range(1, 7)])
    fit = np.array([c["parameters"][f"compliance{i}_mm_per_kN"] for i in range(1, 7)])
    sd = np.array([c["parameter_std"][f"compliance{i}_mm_per_kN"] for i in range(1, 7)])
    z = (fit - true) / sd
    # errors consistent with the standard errors: RMS z of the 6 compliances below the chi^2(6) 99.9 % point
    # (1.93; issue 17's 1.5 is exceeded by chance in 3.6 % of runs; sweep of 30 seeds: 29 within 1.5, worst 1.83)
    assert float(np.sqrt(np.mean(z ** 2))) < 2.0, (msg, z)
    assert int(np.argmax(np.abs(true - np.median(true)))) == int(np.argmax(np.abs(fit - np.median(fit)))), msg
    assert r["extended"]["rms_holdout"]["position_mm"] <= 1.5 * floor_mm(s, "xyzabc"), msg


def test_a_common_compliance_stays_common(cfg):
    seed = fresh_seed()
    s, r = run(cfg, ["elastic_sag"], seed, n_fit=80, n_hold=40)
    assert labels(r) == ["elastic_sag"], (seed, r["verdict"])
    assert r["causes"][0]["variant"]["chosen"] == "common", seed


def test_positions_only_names_a_separable_cause(cfg):
    rng = np.random.default_rng(fresh_seed())
    effect = ["strut_scale", "elastic_sag", "session_offset", "joint_offset"][rng.integers(4)]
    seed = int(rng.integers(2 ** 31))
    s, r = run(cfg, [effect], seed, measured="xyz")
    msg = f"hidden {effect} seed {seed}: verdict {r['verdict']}"
    assert labels(r) == [effect] and not r["inseparable_causes"], msg
    assert r["extended"]["rms_holdout"]["orientation_deg"] is None
    assert r["extended"]["rms_holdout"]["position_mm"] <= 1.5 * floor_mm(s, "xyz"), msg


def test_an_inseparable_cause_is_not_named(cfg):
    """Temperatures that differ by strut but never change: a per-strut expansion looks exactly like a
    gain error of each strut; the diagnosis must say so and ask for other temperatures, not guess."""
    seed = fresh_seed()
    s = synth.generate(cfg, seed, "strut_scale", n_fit=80, n_holdout=40)
    rng = np.random.default_rng(seed)
    T = 20.0 + rng.uniform(2.0, 8.0, 6)
    for m in (s.fit, s.holdout):
        m.T_strut = np.tile(T, (m.n, 1))
    d = diagnose(cfg, s.fit, s.holdout, Options(noise_mm=s.noise_mm, noise_deg=s.noise_deg, frame="base"))
    r = d.result
    msg = f"seed {seed}: verdict {r['verdict']}"
    assert r["causes"] == [], msg
    g = r["inseparable_causes"]
    assert len(g) == 1 and set(g[0]["causes"]) == {"strut_scale", "thermal_expansion"}, msg
    assert "temperatures" in g[0]["what_to_measure"] and "--separate" in g[0]["what_to_measure"]["poses"], msg
    assert r["verdict"].startswith("inseparable: ") and "none" not in r["verdict"], msg
    # the model still predicts: the stand-in explains the data
    assert r["extended"]["rms_holdout"]["position_mm"] <= 1.5 * floor_mm(s, "xyzabc"), msg
