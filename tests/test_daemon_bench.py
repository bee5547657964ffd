"""`hexacnc bench loop`: the bare-loop baseline's overrun rule and the JSON contract (keys only:
timing targets are measured by the benchmark, never asserted in tests)."""
import json
import subprocess
import sys

import pytest

from hexacnc.config import default_config_path, load_config
from hexacnc.daemon import rt
from hexacnc.errors import ConfigError
from hexacnc.daemon.loop import spin_ns
from hexacnc.daemon.shm import PHASE_NAMES


pytestmark = pytest.mark.e2e


def test_bare_loop_measures_its_work_and_counts_every_missed_deadline():
    # work shorter than the period: each cycle's measured compute covers the busy-wait
    r = rt.bare_loop(0.0005, 0.05, spin_ns(500_000, 0.0002) * 1e-9, work_s=0.0001)
    assert r["cycles"] == 100
    assert r["compute_us"]["median"] >= 100.0
    assert r["spin_us"] == 200.0
    # work longer than the period: every cycle overruns, the run never breaks
    r = rt.bare_loop(0.0005, 0.01, 0.0001, work_s=0.0006)
    assert r["cycles"] == 20
    assert r["overruns"] >= r["cycles"]
    assert r["max_overruns_in_row"] == r["overruns"]


def test_spin_comes_from_the_config_capped_to_a_fraction_of_the_period(tmp_path):
    assert spin_ns(500_000, 0.0002) == 200_000
    assert spin_ns(200_000, 0.0002) == 160_000
    assert spin_ns(2_000_000, 0.00035) == 350_000
    assert load_config().cycle.spin_s == 0.0002
    bad = tmp_path / "m.toml"
    bad.write_text(default_config_path().read_text().replace("[cycle]\n", "[cycle]\nspin_s = 0.00045\n", 1))
    with pytest.raises(ConfigError, match=r"spin_s"):
        load_config(str(bad))


@pytest.mark.slow
def test_bench_loop_prints_the_json_contract():
    r = subprocess.run([sys.executable, "-m", "hexacnc", "bench", "loop", "--duration", "1",
                        "--bare-seconds", "0.2"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    for key in ("bench", "period_s", "privileges", "bus_load", "io", "processes", "bare_loop", "targets",
                "load_average_at_start", "other_hexacnc_hot_loops_at_start"):
        assert key in out, key
    assert out["io"]["mode"] == "shm" and out["io"]["frame_batch"] is True
    assert set(out["processes"]) >= {"supervisor", "hot_loop", "simulated_drives"}
    for phase in ("idle", "streaming"):
        ph = out[phase]
        for key in ("lateness_us", "compute_us", "overruns", "overrun_pct", "max_overruns_in_row", "fault"):
            assert key in ph, (phase, key)
        assert ph["cycles"] > 1000
        assert set(ph["compute_phases_us"]) == set(PHASE_NAMES)
        assert all(v["mean"] > 0 for v in ph["compute_phases_us"].values())
    assert out["bare_loop"]["cycles"] == 400
    assert "verdict" in out["targets"]["bare_loop"]
