"""``hexacnc bench plan`` without the bench extra says what to install instead of a traceback."""
from __future__ import annotations

import argparse
import json

from hexacnc.bench import jerkopt
from hexacnc.bench import plan as bench_plan


def _args(**kw):
    p = argparse.ArgumentParser()
    bench_plan.configure(p)
    a = p.parse_args(["--skip-corpus", "--skip-memory"])
    for k, v in kw.items():
        setattr(a, k, v)
    return a


def test_without_toppra_the_bench_names_the_package(monkeypatch, capsys):
    monkeypatch.setattr(bench_plan, "have_toppra", lambda: False)
    assert bench_plan.main(_args()) == 0
    out = capsys.readouterr()
    assert "pip install" in out.err and "toppra" in out.err
    assert "Traceback" not in out.err
    res = json.loads(out.out)
    assert "toppra" in res["topp"]["skipped"]


def test_without_casadi_the_optimum_is_skipped_with_the_install_hint(monkeypatch):
    monkeypatch.setattr(jerkopt, "have_casadi", lambda: False)
    r = jerkopt.jerk_optimum_report(None, None, [])
    assert "casadi" in r["skipped"] and "pip install" in r["skipped"]
