"""`hexacnc bus scan` and the [bus] keys of this issue (nodes, simulate_profile, timeouts, units)."""
import json

import pytest

from drivers.description import DEFAULT_EDS, STRICT_EDS, node_paths
from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.errors import ConfigError



def cfg_file(tmp_path, bus_lines: str):
    from importlib import resources
    text = (resources.files("hexacnc") / "data" / "default.toml").read_text()
    for line in bus_lines.splitlines():             # the test's value replaces the file's own
        key = line.split("=")[0].strip()
        text = "\n".join(t for t in text.split("\n") if t.split("=")[0].strip() != key)
    text = text.replace("[bus]\n", "[bus]\n" + bus_lines + "\n", 1)
    p = tmp_path / "m.toml"
    p.write_text(text)
    return p


def test_scan_lists_every_node_and_matches(tmp_path, capsys):
    rc = cli(["bus", "scan", "--config", str(cfg_file(tmp_path, 'simulate_profile = "strict"')), "--json",
              "--listen-s", "0.2"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["all_match"] and out["simulated"] == "strict"
    nodes = [e for e in out["nodes"] if e["configured"]]
    assert [e["node_id"] for e in nodes] == [1, 2, 3, 4, 5, 6] and all(e["found"] for e in nodes)
    assert {e["vendor_id"] for e in nodes} == {0x1A7} and {e["device_type"] for e in nodes} == {0x00020192}
    assert nodes[0]["software_version"] == "FW 3.2.7 (simulated)" and "csp" in nodes[0]["modes"]


def test_scan_reports_a_mismatch_with_the_config(tmp_path, capsys):
    nodes = ", ".join(f'{{node_id = {i}, vendor_id = {0x1A7 if i != 2 else 0x99}}}' for i in range(1, 7))
    rc = cli(["bus", "scan", "--config", str(cfg_file(tmp_path, f'simulate_profile = "strict"\nnodes = [{nodes}]')),
              "--listen-s", "0.2"])
    out = capsys.readouterr().out
    assert rc == 1
    line = next(ln for ln in out.splitlines() if ln.split()[:2] == ["0", "2"])
    assert "MISMATCH: 0x1018:01 vendor-ID: expected 0x00000099, found 0x000001A7" in line
    assert "configuration does NOT match the bus" in out


def test_bus_nodes_key(tmp_path):
    eds = tmp_path / "d.eds"
    eds.write_text(STRICT_EDS.read_text())
    nodes = ", ".join(f'{{node_id = {i + 10}, eds = "d.eds"}}' if i == 0 else f"{{node_id = {i + 10}}}"
                      for i in range(6))
    cfg = load_config(cfg_file(tmp_path, f"nodes = [{nodes}]"))
    assert cfg.bus.node_ids == (10, 11, 12, 13, 14, 15)
    assert node_paths(cfg.bus) == [str(eds)] + [str(DEFAULT_EDS)] * 5
    assert cfg.bus.boot_timeout_s == 15.0 and cfg.bus.comm_loss_timeout_s == 0.2    # the embedded machine's
    from hexacnc.config import BusConfig
    assert BusConfig().comm_loss_timeout_s == 0.02                                   # the default for real buses
    with pytest.raises(ConfigError, match=r"\[bus\] nodes\[1\]: eds .*nope.eds.*no such file"):
        load_config(cfg_file(tmp_path, 'nodes = [{node_id = 1}, {node_id = 2, eds = "nope.eds"}, '
                                       '{node_id = 3}, {node_id = 4}, {node_id = 5}, {node_id = 6}]'))
    with pytest.raises(ConfigError, match=r"\[bus\] nodes: expected a list of 6 tables"):
        load_config(cfg_file(tmp_path, "nodes = [1, 2]"))
    with pytest.raises(ConfigError, match=r"\[bus\] nodes: node ids \[1, 2, 3, 4, 5, 6\] disagree"):
        load_config(cfg_file(tmp_path, "node_ids = [1, 2, 3, 4, 5, 7]\nnodes = ["
                             + ", ".join(f"{{node_id = {i}}}" for i in range(1, 7)) + "]"))
    with pytest.raises(ConfigError, match=r"\[bus\] simulate_profile: value 'lenient' is not one of"):
        load_config(cfg_file(tmp_path, 'simulate_profile = "lenient"'))
    with pytest.raises(ConfigError, match=r"\[bus\] comm_loss_timeout_s: value 0.0 is below the minimum"):
        load_config(cfg_file(tmp_path, "comm_loss_timeout_s = 0.0"))
