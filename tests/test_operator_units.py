"""Operator control without the daemon: state files, the interpreter adapter, config keys, the
rapid override in the sampler, jog planning."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from hexacnc.config import load_config, parse_config
from hexacnc.errors import ConfigError, DataError
from hexacnc.kinematics import Hexapod
from hexacnc.state import StateStore, ToolEntry, interpret, read_tool_table, write_tool_table
from hexacnc.state.files import parse_tool_table, parse_var_file
from hexacnc.state.machine import PERSISTENT


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


HOME_TIP = [0.0, 0.0, -1150.0, 0.0, 0.0, 0.0]


def test_tool_table_round_trip_in_linuxcnc_format(tmp_path):
    tools = {1: ToolEntry(1, 4, 62.5, 6.0, "6 mm end mill"), 12: ToolEntry(12, 12, -0.25, 0.0, "")}
    p = tmp_path / "tool.tbl"
    write_tool_table(p, tools)
    assert p.read_text().splitlines()[0] == "T1 P4 Z62.500000 D6.000000 ;6 mm end mill"
    assert read_tool_table(p) == tools
    # LinuxCNC's own lines, with words we ignore
    got = parse_tool_table("T3 P3 X0 Y0 Z+10.5 A0 D2.5 I0 J0 Q0 ;drill\n\n;comment only\n", "t")
    assert got == {3: ToolEntry(3, 3, 10.5, 2.5, "drill")}


@pytest.mark.parametrize("text,where", [("T1 P1 Z10\nT1 P2 Z3\n", "t:2"), ("P1 Z3\n", "t:1"),
                                        ("T1 Zfoo\n", "t:1"), ("T1 Z5000\n", "t:1"), ("T-2 Z1\n", "t:1")])
def test_bad_tool_table_names_file_and_line(text, where):
    with pytest.raises(DataError) as ei:
        parse_tool_table(text, "t")
    assert str(ei.value).startswith(where)


def test_var_file_reads_only_persistent_numbers_and_names_bad_lines():
    got = parse_var_file("5221\t1.5\n5222 -2\n31 7\n", "v", PERSISTENT)
    assert got == {5221: 1.5, 5222: -2.0}
    with pytest.raises(DataError, match="v:2"):
        parse_var_file("5221 1\n5222 nan\n", "v", PERSISTENT)


def test_atomic_write_leaves_no_temporary_and_replaces(tmp_path):
    p = tmp_path / "tool.tbl"
    write_tool_table(p, {1: ToolEntry(1, 1, 1.0)})
    write_tool_table(p, {2: ToolEntry(2, 2, 2.0)})
    assert os.listdir(tmp_path) == ["tool.tbl"]
    assert list(read_tool_table(p)) == [2]


def test_offsets_g92_and_system_persist_through_the_adapter(cfg, tmp_path):
    store = StateStore(cfg, tmp_path)
    prog, new = interpret("G10 L2 P2 X5 Y6 Z-1100\nG55\nG92 X1\nG1 X3 F600\n", "p", cfg, HOME_TIP,
                          store.snapshot())
    # G55 x origin 5; G92 X1 at machine x 0 makes the G92 offset 0 - 5 - 1 = -6; X3 -> machine 3 + 5 - 6
    assert new.g92()[0] == pytest.approx(-6.0)
    assert prog.motion_blocks[-1].end[0] == pytest.approx(2.0)
    store.commit(new)
    again = StateStore(cfg, tmp_path).snapshot()
    assert again.system == 2 and again.offset(2)[:3] == [5.0, 6.0, -1100.0]
    assert again.g92()[0] == pytest.approx(new.g92()[0]) and again.g92()[0] != 0.0
    # the next program runs in G55 with G92: X0 there is where G92 put it
    prog2, _ = interpret("G1 X0 F600\n", "q", cfg, HOME_TIP, again)
    assert prog2.blocks[-1].end[0] == pytest.approx(5.0 + again.g92()[0])


def test_modal_state_carries_over(cfg, tmp_path):
    store = StateStore(cfg, tmp_path)
    _, s1 = interpret("G91 G1 X1 F300\n", "a", cfg, HOME_TIP, store.snapshot())
    prog, s2 = interpret("X2\n", "b", cfg, HOME_TIP, s1)          # G91 G1 F300 still active
    b = prog.motion_blocks[0]
    assert b.kind == "line" and b.end[0] - b.start[0] == pytest.approx(2.0)
    assert b.feed_mm_s == pytest.approx(5.0)


def test_store_edits_and_refusals(cfg, tmp_path):
    store = StateStore(cfg, tmp_path)
    store.set_offset("g57", {"x": 1, "C": 2})
    assert store.snapshot().offset(4)[0] == 1.0 and store.snapshot().offset(4)[5] == 2.0
    with pytest.raises(DataError):
        store.set_offset("G60", {"x": 1})
    with pytest.raises(DataError):
        store.set_offset("G54", {"q": 1})
    store.set_tool(ToolEntry(5, 5, 30.0, 4.0, "x"))
    assert (tmp_path / "tool.tbl").read_text().startswith("T1 ")
    with pytest.raises(DataError):
        store.set_tool(ToolEntry(5, 5, math.inf))
    store.delete_tool(5)
    assert 5 not in StateStore(cfg, tmp_path).snapshot().tools


def _doc(cfg, **sections):
    doc = {k: dict(v) if isinstance(v, dict) else v for k, v in cfg.raw.items()}
    for name, kv in sections.items():
        doc.setdefault(name, {}).update(kv)
    return doc


@pytest.mark.parametrize("section,key,value", [("planner", "max_feed_override", 2.5),
                                               ("planner", "max_feed_override", 0.5),
                                               ("jog", "deadman_s", 0.5), ("jog", "speed_mm_s", -1.0),
                                               ("homing", "method", "magic"), ("homing", "required", "yes"),
                                               ("workspace", "pivot_mm", [0, 0]), ("jog", "bogus", 1)])
def test_operator_config_keys_are_range_checked(cfg, section, key, value):
    with pytest.raises(ConfigError) as ei:
        parse_config(_doc(cfg, **{section: {key: value}}), "m.toml")
    assert f"m.toml: [{section}]" in str(ei.value) and (key in str(ei.value))


def test_operator_config_keys_parse(cfg):
    c = parse_config(_doc(cfg, planner={"max_feed_override": 1.2}, jog={"deadman_s": 0.03},
                          homing={"method": "cia402", "required": True}, workspace={"pivot_mm": [0, 0, -100]}),
                     "m.toml")
    assert c.operator.max_feed_override == 1.2 and c.operator.jog.deadman_s == 0.03
    assert c.operator.homing.method == "cia402" and c.operator.homing.required
    assert c.operator.pivot_mm.tolist() == [0.0, 0.0, -100.0]


def _plan(cfg, text):
    from hexacnc.gcode import program_from_config
    from hexacnc.planner import plan_program
    prog = program_from_config(text, "r", cfg)
    return plan_program(prog.blocks, cfg, hexapod=Hexapod(cfg), period_s=cfg.cycle.period_s)


def _play(plan, period, rapid=1.0, feed=1.0):
    s = plan.sampler(period)
    s.set_override(feed)
    s.set_rapid_override(rapid)
    out = np.empty((4000, 8))
    rows = []
    while not s.done:
        n = s.next_rows(out)
        rows.append(out[:n].copy())
    return np.vstack(rows)


def test_rapid_override_slows_rapids_only(cfg):
    text = "G21 G90 G61\nG0 X0 Y0 Z60\nG0 X60\nG1 X0 F600\nM2\n"
    plan = _plan(cfg, text)
    p = cfg.cycle.period_s
    full = _play(plan, p)
    half = _play(plan, p, rapid=0.25)
    line = lambda rows, ln: int(np.sum(rows[:, 6] == ln))   # noqa: E731  rows spent on a line
    assert line(half, 3) > 2.0 * line(full, 3)                # the 60 mm G0 takes much longer
    assert line(half, 4) == pytest.approx(line(full, 4), rel=0.03)   # the G1 does not change
    assert np.allclose(half[-1, :6], full[-1, :6])
    with pytest.raises(ValueError):
        plan.sampler(p).set_rapid_override(float("nan"))


def test_jog_plan_reach_and_rotation_about_the_tip(cfg):
    from hexacnc.daemon.jog import JogSource, plan_jog, tip_poses
    from hexacnc.config.operator import tip_box
    hx = Hexapod(cfg)
    tip = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    jp = plan_jog(cfg, hx, cfg.home_pose, "x", "base", tip, 0.0)
    lo, hi = tip_box(cfg)
    assert jp.s_hi == pytest.approx(hi[0], abs=0.01) and jp.s_lo == pytest.approx(lo[0], abs=0.01)
    assert "soft limit" in jp.why_hi
    rot = plan_jog(cfg, hx, cfg.home_pose, "b", "tool", tip, 0.0)
    X = rot.pose_of([0.0, 3.0])
    t = tip_poses(cfg, X, 0.0)
    assert np.allclose(t[1, :3], t[0, :3], atol=1e-9) and t[1, 4] == pytest.approx(3.0)
    src = JogSource(jp, 0.5, cfg.cycle.period_s)
    rows = src.next_rows(100000)
    assert src.finished and rows[-1, 0] == pytest.approx(cfg.home_pose[0] + 0.5, abs=1e-9)
    v = np.diff(rows[:, 0]) / cfg.cycle.period_s
    assert np.max(np.abs(v)) <= jp.v * 1.0001
    # strut jog: strut 2 changes by the step, the others to first order not at all
    sj = plan_jog(cfg, hx, cfg.home_pose, "2", "base", tip, 0.0)
    L = hx.inverse_batch(sj.pose_of([0.0, 0.1]))
    d = L[1] - L[0]
    assert d[1] == pytest.approx(0.1, abs=1e-4) and np.max(np.abs(np.delete(d, 1))) < 1e-4


def test_homing_gate_and_cia402_not_implemented(cfg, tmp_path):
    import dataclasses
    from types import SimpleNamespace

    from hexacnc.daemon import shm as S
    from hexacnc.daemon.operator import Operator, OperatorError
    hm = dataclasses.replace(cfg.operator.homing, method="cia402", required=True)
    c = cfg.replace(operator=dataclasses.replace(cfg.operator, homing=hm, state_dir=str(tmp_path)))
    h = np.zeros(S.N_HEADER, dtype=np.int64)
    h[S.H_STATE] = S.ST_IDLE
    fake = SimpleNamespace(cfg=c, sh=SimpleNamespace(h=h), alive=True)
    op = Operator(fake)
    assert op.referenced is False
    with pytest.raises(OperatorError) as ei:
        op._motion_checks("program 'p'")
    assert ei.value.code == "invalid_state" and "not referenced" in str(ei.value)
    op._motion_checks("jog", cartesian=False)               # strut jogs stay allowed
    hm2 = dataclasses.replace(hm, method="absolute")
    c2 = c.replace(operator=dataclasses.replace(c.operator, homing=hm2))
    op2 = Operator(SimpleNamespace(cfg=c2, sh=fake.sh, alive=True))
    assert op2.referenced is True
    op2._motion_checks("program 'p'")


@pytest.mark.parametrize("argv, words", [
    (["tools", "3", "z=abc"], ["hexacnc tools", "z_mm", "'abc'", "not a number"]),
    (["tools", "3", "p=1.5"], ["pocket", "'1.5'", "not an integer"]),
    (["tools", "--delete"], ["name the tool"]),
    (["offsets", "G55", "x=1O"], ["hexacnc offsets", "x = '1O'", "not a number"]),
    (["offsets", "x=1"], ["offsets", "name the system"]),
])
def test_tools_and_offsets_refuse_bad_values_on_stderr_before_connecting(capsys, argv, words):
    """A bad value is named with its key, on stderr, exit 2, and nothing reaches a daemon (none runs here)."""
    from hexacnc.cli import main
    rc = main(argv + ["--socket", "/nonexistent/hexacnc.sock"])
    out, err = capsys.readouterr()
    assert rc == 2 and out == "", (rc, out, err)
    assert len(err.strip().splitlines()) == 1
    for w in words:
        assert w in err, err


def test_a_rapid_override_ends_at_the_rapids_stop_within_the_limits(cfg):
    """After a rapid at 25 % and an exact stop, the feed move starts at its own rate: the rate changes at rest,
    where it changes no strut speed or acceleration (it ramped up through the feed move's first 0.3 s). The rows
    stay within the strut limits, measured by exact inverse kinematics and finite differences."""
    from test_planner_motion import utilisation
    text = ("G21 G90 G61\nG0 X0 Y0 Z60\nG0 X60\nG1 X0 F600\nG0 Y40 Z50\nG1 Y0 Z60 A5 F900\n"
            "G64 P0.01\nG0 X30\nG1 X0 F1200\nM2\n")
    plan = _plan(cfg, text)
    p = cfg.cycle.period_s
    full = _play(plan, p)
    slow = _play(plan, p, rapid=0.25)
    line = lambda rows, ln: int(np.sum(rows[:, 6] == ln))   # noqa: E731
    for ln in (4, 6):                                        # feed moves after a rapid's exact stop
        assert abs(line(slow, ln) - line(full, ln)) <= 2, (ln, line(slow, ln), line(full, ln))
    assert line(slow, 8) > 2.0 * line(full, 8)                # the G64 rapid, slowed
    assert line(slow, 9) >= line(full, 9)                    # its blend into the feed move: a ramp, no jump
    u = utilisation(cfg, slow, p)
    assert u[0] <= 1.0 and u[1] <= 0.95 and u[2] <= 0.95, u
    for ln in (4, 6):            # the feed moves from the stop on: as at full rapid rate, no step from the change
        a, b = (np.nonzero(rows[:, 6] == ln)[0][[0, -1]] for rows in (slow, full))
        us, uf = utilisation(cfg, slow[a[0] - 3:a[1]], p), utilisation(cfg, full[b[0] - 3:b[1]], p)
        assert all(x <= y + 0.01 for x, y in zip(us, uf)), (ln, us, uf)
