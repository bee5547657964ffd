"""The architecture figures (``hexacnc bench arch``) of this tree, and the measuring code itself."""
from __future__ import annotations

import textwrap
from pathlib import Path

from hexacnc.bench import arch

REPO = Path(__file__).resolve().parents[1]


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        p = tmp_path / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text))
    for pkg in ("hexacnc", "drivers"):
        (tmp_path / pkg).mkdir(exist_ok=True)
        (tmp_path / pkg / "__init__.py").touch()
    return tmp_path


def test_measure_finds_cycles_layers_private_names_and_long_functions(tmp_path):
    long_body = "\n".join(f"    x{i} = {i}" for i in range(120))
    root = _tree(tmp_path, {
        "hexacnc/a.py": "from . import b\n",
        "hexacnc/b.py": "def f():\n    from .a import thing\n",           # function-level import: still a cycle
        "hexacnc/sim/__init__.py": "",
        "hexacnc/sim/s.py": "from ..daemon import d\n",
        "hexacnc/daemon/__init__.py": "",
        "hexacnc/daemon/d.py": "from ..sim.s import _private\n",
        "drivers/m.py": "from hexacnc.errors import BusError\n",
        "hexacnc/errors.py": "class BusError(Exception):\n    pass\n",
        "hexacnc/long.py": "def big():\n" + long_body + "\n",
    })
    out = arch.measure(root)
    assert out["import_cycles"] == [["hexacnc.a", "hexacnc.b"], ["hexacnc.daemon.d", "hexacnc.sim.s"]]
    assert ["hexacnc.daemon", "hexacnc.sim"] in out["package_cycles"]
    assert {v["rule"] for v in out["layer_violations"]} == {
        "the drive layer depends on nothing in hexacnc", "the simulator never imports the daemon"}
    assert out["private_cross_package"] == [{"module": "hexacnc.daemon.d", "line": 1,
                                             "imports": "hexacnc.sim.s._private"}]
    assert [f["function"] for f in out["long_functions"]] == ["hexacnc.long:big"]


def test_type_checking_imports_do_not_count(tmp_path):
    root = _tree(tmp_path, {
        "hexacnc/a.py": "from . import b\n",
        "hexacnc/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n",
    })
    assert arch.measure(root)["import_cycles"] == []


def test_this_tree_has_no_import_cycles():
    out = arch.measure(REPO)
    assert out["import_cycles"] == [], out["import_cycles"]
    assert out["package_cycles"] == [], out["package_cycles"]


def test_this_tree_has_no_layer_violations():
    """``drivers/`` depends on nothing in ``hexacnc``; the core and the simulator never import the daemon."""
    out = arch.measure(REPO)
    assert out["layer_violations"] == [], out["layer_violations"]
