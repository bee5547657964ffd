"""Measurement CSV contract, column mappings, bad input (hexacnc.calib.measurements)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hexacnc.calib.measurements import load_mapping, load_measurements
from hexacnc.errors import DataError

REPO = Path(__file__).resolve().parent.parent
JUGGLEBOT = REPO.parent / "shared" / "data" / "jugglebot"
HEADER = "q1,q2,q3,q4,q5,q6,x,y,z,a,b,c"


def write(tmp_path, text, name="m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_contract_columns_partial_and_optional(tmp_path):
    p = write(tmp_path, "q1,q2,q3,q4,q5,q6,z,a,session,T_frame,payload_kg,t_s\n"
                        "1,2,3,4,5,6,-900.5,,A,20.5,0,0.0\n"
                        "1,2,3,4,5,7,,0.25,B,21.0,5,1.5\n")
    m = load_measurements(p)
    assert m.n == 2
    assert m.q[1, 5] == 7.0
    assert m.measured_names() == ["z", "a"]
    assert m.mask.tolist() == [[False, False, True, False, False, False], [False, False, False, True, False, False]]
    assert m.sessions() == ["A", "B"]
    assert m.strut_temperatures().shape == (2, 6)
    assert m.payload_kg.tolist() == [0.0, 5.0]


def test_quaternion_converted_to_abc(tmp_path):
    # 30 deg about z: q = (0, 0, sin 15, cos 15)
    s, c = math.sin(math.radians(15)), math.cos(math.radians(15))
    p = write(tmp_path, f"q1,q2,q3,q4,q5,q6,x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1,2,3,0,0,{s},{c}\n")
    m = load_measurements(p)
    assert np.allclose(m.y[0], [1, 2, 3, 0, 0, 30], atol=1e-9)


def test_direction_from_row_order(tmp_path):
    rows = "\n".join(f"{q},0,0,0,0,0,0,0,0,0,0,0" for q in (5, 7, 7, 3, 4))
    m = load_measurements(write(tmp_path, HEADER + "\n" + rows + "\n"))
    assert m.direction()[:, 0].tolist() == [1, 1, 1, -1, 1]


@pytest.mark.parametrize("text, words", [
    ("", ["empty file"]),
    ("q1,q2,q3,q4,q5,x\n1,2,3,4,5,6\n", ["q6"]),
    (HEADER + ",foo\n" + "0,0,0,0,0,0,0,0,0,0,0,0,1\n", ["unknown column", "foo"]),
    (HEADER + "\n0,0,0,0,0,0,0,0,0,0,0\n", ["line 2", "fields"]),
    (HEADER + "\n0,0,0,0,nan,0,0,0,0,0,0,0\n", ["line 2", "q5", "not finite"]),
    (HEADER + "\n0,0,0,0,,0,0,0,0,0,0,0\n", ["line 2", "q5", "empty"]),
    (HEADER + "\n0,0,0,zero,0,0,0,0,0,0,0,0\n", ["line 2", "q4", "not a number"]),
    ("q1,q2,q3,q4,q5,q6,x,qx,qy\n0,0,0,0,0,0,1,0,0\n", ["quaternion", "qz"]),
    ("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n", ["no measured coordinate"]),
    (HEADER + "\n0,0,0,0,0,0,,,,,,\n", ["no row has a measured coordinate"]),
    ("q1,q2,q3,q4,q5,q6,z,z\n0,0,0,0,0,0,1,1\n", ["duplicate", "z"]),
])
def test_bad_input_names_what_and_where(tmp_path, text, words):
    p = write(tmp_path, text)
    with pytest.raises(DataError) as ei:
        load_measurements(p)
    msg = str(ei.value)
    assert str(p) in msg
    for w in words:
        assert w in msg, msg


def test_mapping_with_scale_and_errors(tmp_path):
    mp = write(tmp_path, '[columns]\nq1 = { column = "L1", scale = 2.0, offset = 1.0 }\n'
                         + "".join(f'q{i} = "L{i}"\n' for i in range(2, 7)) + 'z = "height"\n'
                         + 'ignore = ["note"]\n', "map.toml")
    # 'ignore' inside [columns] is a mistake: the loader must say so
    with pytest.raises(DataError, match="ignore"):
        load_mapping(mp)
    mp.write_text('ignore = ["note"]\n[columns]\nq1 = { column = "L1", scale = 2.0, offset = 1.0 }\n'
                  + "".join(f'q{i} = "L{i}"\n' for i in range(2, 7)) + 'z = "height"\n')
    data = write(tmp_path, "L1,L2,L3,L4,L5,L6,height,note\n3,0,0,0,0,0,-5,hello\n")
    m = load_measurements(data, mp)
    assert m.q[0, 0] == 7.0 and m.y[0, 2] == -5.0
    # an unmapped, unignored source column is an error
    data2 = write(tmp_path, "L1,L2,L3,L4,L5,L6,height,extra\n3,0,0,0,0,0,-5,1\n", "d2.csv")
    with pytest.raises(DataError, match="extra"):
        load_measurements(data2, mp)
    bad = write(tmp_path, '[columns]\nq9 = "L1"\n', "bad.toml")
    with pytest.raises(DataError, match="q9"):
        load_mapping(bad)


def test_jugglebot_files_load_through_shipped_mapping():
    if not JUGGLEBOT.exists():
        pytest.skip(f"real data not present at {JUGGLEBOT}")
    mp = REPO / "config" / "jugglebot-columns.toml"
    m = load_measurements(JUGGLEBOT / "calibration_108_poses.csv", mp)
    h = load_measurements(JUGGLEBOT / "validation_60_poses.csv", mp)
    assert (m.n, h.n) == (108, 60)
    assert m.full_pose_rows().all()
    # first row: leg 1 = 1.6767652 rev at 1 / (13.21144e-3) mm/rev
    assert m.q[0, 0] == pytest.approx(1.6767652 / 13.21144e-3, rel=1e-8)
    assert m.y[0, 2] == pytest.approx(751.5284423828125)
