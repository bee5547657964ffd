"""The socket op "temperatures" against the real daemon ([thermal] source = "socket").

A valid reading changes the estimate; a bad one (NaN, out of range, wrong count, missing field,
time going backwards) gets an error reply naming the field and changes nothing; the applied
offsets never move faster than [thermal] max_offset_rate_mm_s nor beyond max_offset_mm; stale
probes raise a warning and freeze the offsets.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P

from e2e_fixtures import machine, client  # noqa: F401  (shared fixtures; cfg is overridden below)

pytestmark = pytest.mark.e2e


RATE_MM_S = 0.0035
MAX_MM = 0.002
STALE_S = 2.0


@pytest.fixture(scope="module")
def cfg():
    base = load_config(None)
    cycle = dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0)
    thermal = dataclasses.replace(base.thermal, source="socket", max_offset_rate_mm_s=RATE_MM_S,
                                  max_offset_mm=MAX_MM, stale_after_s=STALE_S)
    return base.replace(cycle=cycle, thermal=thermal)


def _reading(T_struts, ambient=20.0, frame=20.0):
    return {"struts": [[float(T_struts)] * 2 for _ in range(6)], "ambient": ambient, "frame": frame}


def _th(c, settle_s: float = 10.0):
    """The thermal status once every accepted reading has gone through the observer."""
    t_end = time.monotonic() + settle_s
    while True:
        th = c.call("status")["thermal"]
        if th["pending"] == 0 or time.monotonic() > t_end:
            return th
        time.sleep(0.02)


def _err(c, **fields):
    r = c.call("temperatures", check=False, **fields)
    assert r["ok"] is False, r
    return r["error"]


def test_valid_push_changes_the_estimate(cfg, client):
    th = _th(client)
    assert th["source"] == "socket" and th["state"] in ("waiting", "ok", "stale")
    r = client.call("temperatures", probes_C=_reading(20.0), spindle_C=20.0)
    assert r["accepted"] is True
    time.sleep(0.2)
    a = _th(client)
    assert a["state"] == "ok" and a["readings"] >= 1
    r = client.call("temperatures", probes_C=[21.0] * 12 + [20.0, 20.0], spindle_C=21.0)   # flat list form
    time.sleep(0.2)
    b = _th(client)
    assert b["readings"] == a["readings"] + 1
    assert b["probes_C"]["struts"] == [[21.0, 21.0]] * 6 and b["probes_C"]["spindle"] == 21.0
    assert np.all(np.array(b["strut_mean_C_est"]) > np.array(a["strut_mean_C_est"]))
    assert np.all(np.array(b["strut_offsets_est_mm"]) > np.array(a["strut_offsets_est_mm"]))
    assert b["spindle_growth_est_mm"] == pytest.approx(cfg.spindle.growth_mm_per_K * 1.0)


@pytest.mark.parametrize("fields,code,field", [
    ({"probes_C": {"struts": [[20.0, 20.0]] * 5 + [[20.0, math.nan]], "ambient": 20.0, "frame": 20.0}},
     "bad_value", "probes_C.struts[5][1]"),
    ({"probes_C": [20.0] * 13}, "bad_value", "probes_C"),
    ({"probes_C": {"struts": [[20.0, 20.0]] * 5, "ambient": 20.0, "frame": 20.0}}, "bad_value", "probes_C.struts"),
    ({"probes_C": {"struts": [[20.0]] * 6, "ambient": 20.0, "frame": 20.0}}, "bad_value", "probes_C.struts[0]"),
    ({"probes_C": {"struts": [[20.0, 20.0]] * 6, "ambient": 20.0}}, "missing_field", "probes_C.frame"),
    ({"spindle_C": 20.0}, "missing_field", "probes_C"),
    ({"probes_C": "hot"}, "bad_type", "probes_C"),
    ({"probes_C": [20.0] * 13 + [float("inf")]}, "bad_value", "probes_C[13]"),
    ({"probes_C": [20.0] * 12 + [500.0, 20.0]}, "bad_value", "probes_C[12]"),
    ({"probes_C": [20.0] * 14, "spindle_C": math.nan}, "bad_value", "spindle_C"),
    ({"probes_C": [20.0] * 14, "time_s": -1.0}, "bad_value", "time_s"),
])
def test_bad_readings_are_refused_naming_the_field_and_change_nothing(cfg, client, fields, code, field):
    client.call("temperatures", probes_C=_reading(21.0), spindle_C=21.0)    # fresh: nothing goes stale meanwhile
    before = _th(client)
    e = _err(client, **fields)
    assert e["code"] == code and e["field"] == field, e
    assert field.split("[")[0].split(".")[0] in e["message"] or field in e["message"]
    time.sleep(0.1)
    after = _th(client)
    # (type and presence errors are refused by the protocol layer before the daemon counts them)
    assert after["readings"] == before["readings"] and after["rejected"] - before["rejected"] in (0, 1)
    assert after["probes_C"] == before["probes_C"]
    assert after["strut_offsets_est_mm"] == before["strut_offsets_est_mm"]
    assert after["spindle_growth_est_mm"] == before["spindle_growth_est_mm"]
    assert after["strut_mean_C_est"] == before["strut_mean_C_est"] and after["time_s"] == before["time_s"]


def test_time_must_advance(client):
    client.call("temperatures", probes_C=[20.0] * 14, time_s=100000.0)
    e = _err(client, probes_C=[20.0] * 14, time_s=99999.0)
    assert e["code"] == "bad_value" and e["field"] == "time_s"
    client.call("temperatures", probes_C=[20.0] * 14, time_s=100001.0)


def test_offsets_are_rate_and_magnitude_limited(cfg, client):
    client.call("temperatures", probes_C=_reading(20.0), spindle_C=20.0, time_s=200000.0)
    time.sleep(0.3)
    t0 = time.monotonic()
    th0 = _th(client)
    o0, c0, tgt0 = np.array(th0["offsets_mm"]), th0["loop_cycles"], np.array(th0["strut_offsets_target_mm"])
    # a jump of 40 K in every probe: the estimate jumps by ~0.4 mm; the offsets must not
    t_s = 200001.0
    series = []
    while time.monotonic() - t0 < 1.2:
        client.call("temperatures", probes_C=_reading(60.0, 20.0, 20.0), spindle_C=60.0, time_s=t_s)
        t_s += 1.0
        th = _th(client)
        series.append((time.monotonic(), th["loop_cycles"], np.array(th["offsets_mm"]), th["spindle_growth_mm"],
                       np.array(th["strut_offsets_target_mm"])))
        time.sleep(0.1)
    th = _th(client)
    assert np.all(np.array(th["strut_offsets_est_mm"]) > 0.1)          # the observer believes the jump
    period = cfg.cycle.period_s
    for t, c, o, g, tgt in series:
        # targets (supervisor, wall clock, ramped every 50 ms tick): one tick of slack before th0
        assert np.all(np.abs(tgt - tgt0) <= RATE_MM_S * (t - t0 + 0.1) + 1e-9)
        # applied (hot loop, slewed every 16 cycles; a sample's offsets are up to 8 cycles older than its count)
        allow = RATE_MM_S * period * (c - c0 + 24) + 1e-9
        assert np.all(np.abs(o - o0) <= allow), (c - c0, (o - o0).tolist())
        assert np.all(np.abs(o) <= MAX_MM + 1e-12) and abs(g) <= MAX_MM + 1e-12
        assert np.all(np.abs(tgt) <= MAX_MM + 1e-12)
    assert np.all(series[-1][2] > 0.5 * MAX_MM)                         # it did move, up to the clamp


def test_stale_probes_warn_and_freeze_the_offsets(cfg, client):
    client.call("temperatures", probes_C=_reading(30.0), spindle_C=30.0, time_s=300000.0)
    time.sleep(STALE_S + 0.4)
    t_end = time.monotonic() + 5.0
    while _th(client)["state"] != "stale" and time.monotonic() < t_end:
        time.sleep(0.05)
    a = _th(client)
    assert a["state"] == "stale" and "stale" in a["warning"]
    assert a["probes_age_s"] > STALE_S
    assert a["strut_offsets_target_mm"] == pytest.approx(a["offsets_mm"], abs=1e-12)
    time.sleep(0.3)
    b = _th(client)
    assert b["offsets_mm"] == a["offsets_mm"] and b["spindle_growth_mm"] == a["spindle_growth_mm"]
    client.call("temperatures", probes_C=_reading(30.0), spindle_C=30.0, time_s=300010.0)
    time.sleep(0.2)
    c = _th(client)
    assert c["state"] == "ok" and c["warning"] is None


def test_temperatures_op_is_known_and_documented_in_hello(client):
    assert "temperatures" in client.call("hello")["ops"]
    assert "temperatures" in P.OPS
