"""End to end through the real daemon (simulated drives): programs without motion end cleanly where the
machine stands, and ``hexacnc send`` streams a program in chunks that then runs to its end."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.daemon import core  # noqa: F401  (a broken import fails the suite, never skips it)

from e2e_fixtures import cfg, machine, client  # noqa: E402,F401  (shared fixtures)

from test_e2e_socket import work  # noqa: E402

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


@pytest.mark.parametrize("text", ["", "(comment only)\n", "M2\n", "G4 P0.05\nM2\n"])
def test_programs_without_motion_end_cleanly_through_the_daemon(client, text):
    before = client.call("status")
    r = client.call("program", text=text, name="still", reply_timeout_s=120.0)
    assert r["ok"]
    st = client.call("wait", timeout_s=60.0)
    assert st["state"] == "idle" and st["fault"] is None and st["timed_out"] is False
    # not one increment moved (the pose goes tool tip -> platform and back: 1e-13 mm of rounding)
    np.testing.assert_allclose(st["struts_cmd_mm"], before["struts_cmd_mm"], atol=1e-9)
    np.testing.assert_allclose(st["pose_cmd"], before["pose_cmd"], atol=1e-9)


def test_send_streams_a_program_in_chunks_and_it_runs_to_its_end(cfg, machine, tmp_path, capsys):
    from hexacnc.cli import main as cli
    _daemon, srv = machine
    lines = ["G21 G90 G64 P0.05"]
    for k in range(120):
        lines.append(f"G1 {work(cfg, 5 + (k % 7), 5 - (k % 5), -1140)} F6000  (line {k} of a program sent in pieces)")
    lines.append("M2")
    p = tmp_path / "chunked.ngc"
    p.write_text("\n".join(lines) + "\n")
    assert p.stat().st_size > 3 * 1024
    rc = cli(["send", str(p), "--socket", srv.socket_path, "--chunk-bytes", "1024"])
    out = capsys.readouterr()
    assert rc == 0, out
    assert "upload" in out.err and "100.0 %" in out.err
    assert "finished" in out.out
