"""Protocol module without sockets: decoder, validation, error mapping, plain conversion."""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from hexacnc.daemon import protocol as P
from hexacnc.errors import GcodeError, HexacncError, KinematicsError, PlanError, ProtocolError


def test_decoder_splits_back_to_back_maps_fed_in_odd_chunks():
    msgs = [{"id": i, "op": "status", "pad": "x" * i} for i in range(50)]
    data = b"".join(msgpack.packb(m) for m in msgs)
    dec = P.Decoder()
    out = []
    for k in range(0, len(data), 7):
        dec.feed(data[k:k + 7])
        out.extend(dec.messages())
    assert out == msgs


def test_decoder_rejects_garbage_and_oversize():
    dec = P.Decoder()
    dec.feed(b"\xc1")
    with pytest.raises(ProtocolError):
        list(dec.messages())
    small = P.Decoder(max_bytes=1024)
    with pytest.raises(ProtocolError):
        small.feed(msgpack.packb({"id": 1, "op": "program", "text": "x" * 5000, "name": "n"}))
    assert small.too_large


def test_validate_accepts_ints_for_floats_and_caps_wait():
    r = P.validate_request({"id": 3, "op": "wait", "timeout_s": 10 ** 9})
    assert r.op == "wait" and r.fields["timeout_s"] == P.MAX_WAIT_S
    r = P.validate_request({"id": 4, "op": "subscribe", "rate_hz": 5})
    assert r.fields["rate_hz"] == 5.0
    r = P.validate_request({"id": -1, "op": "hello", "client": None})
    assert r.fields == {}


def test_a_bool_field_takes_a_bool():
    """'delete' was refused as 'must be bool, got bool': every bool was kept out of every field (so that
    True is never an int), the bool fields too (hexacnc tools 3 --delete could not delete)."""
    r = P.validate_request({"id": 1, "op": "tools", "tool": 3, "delete": True})
    assert r.fields == {"tool": 3, "delete": True}


@pytest.mark.parametrize("msg,code", [
    ({"id": 1, "op": "program", "text": "G0\x00", "name": "n"}, "bad_value"),
    ({"id": 1, "op": "wait", "timeout_s": float("inf")}, "bad_value"),
    ({"id": 1, "op": "wait", "timeout_s": True}, "bad_type"),
    ({"id": 1, "op": "unsubscribe", "sub": "1"}, "bad_type"),
    ({"id": 1, "op": "hello", "token": 5}, "bad_type"),
    ({"id": 1, "op": "tools", "tool": True}, "bad_type"),
    ({"id": 1, "op": "tools", "tool": 3, "delete": 1}, "bad_type"),
])
def test_validate_rejects(msg, code):
    with pytest.raises(P.RequestError) as ei:
        P.validate_request(msg)
    assert ei.value.code == code
    rep = ei.value.reply()
    assert rep["id"] == 1 and rep["ok"] is False and rep["error"]["line"] is None


def test_error_mapping_keeps_line_column_and_limit():
    e = P.error_from_exception(GcodeError("unknown word", line=7, column=3, code="syntax"), 5)["error"]
    assert (e["code"], e["line"], e["column"], e["reason"]) == ("gcode", 7, 3, "syntax")
    e = P.error_from_exception(GcodeError("G33", line=2, column=1, code="unsupported"), 5)["error"]
    assert e["code"] == "unsupported"
    e = P.error_from_exception(PlanError("too long", line=9, limit="strut 2 max_length_mm"), 5)["error"]
    assert (e["code"], e["line"], e["limit"]) == ("limit", 9, "strut 2 max_length_mm")
    e = P.error_from_exception(PlanError("no motion", limit="input", code="empty"), 5)["error"]
    assert e["code"] == "gcode" and e["reason"] == "empty" and e["line"] is None
    assert P.error_from_exception(KinematicsError("unreachable"), 5)["error"]["code"] == "limit"
    assert P.error_from_exception(HexacncError("in fault"), 5, "fault")["error"]["code"] == "fault"
    assert P.error_from_exception(HexacncError("queued"), 5, "running", "program")["error"]["code"] == "busy"
    assert P.error_from_exception(HexacncError("not paused"), 5, "idle", "resume")["error"]["code"] == \
        "invalid_state"
    assert P.error_from_exception(HexacncError("no"), 5, "idle", "program")["error"]["code"] == "refused"
    e = P.error_from_exception(ZeroDivisionError("x"), 5)["error"]
    assert e["code"] == "internal" and "ZeroDivisionError" in e["message"]
    for code in (e["code"],):
        assert code in P.ERROR_CODES


def test_plain_and_encode_numpy_status():
    st = {"pose_cmd": np.arange(6.0), "n": np.int64(3), "t": (1, 2), "f": np.float32(0.5),
          "nested": {"v": np.array([[1, 2]])}, "nan": float("nan")}
    out = msgpack.unpackb(P.encode(st), raw=False)
    assert out["pose_cmd"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0] and out["n"] == 3 and out["t"] == [1, 2]
    assert out["f"] == 0.5 and out["nested"]["v"] == [[1, 2]] and math.isnan(out["nan"])
