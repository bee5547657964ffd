"""``hexacnc bench arch``: the architecture figures of the source tree, as JSON.

Measured on the installed packages ``hexacnc`` and ``drivers`` by reading their source (nothing is
imported or run):

- ``import_cycles``: strongly connected groups of modules in the import graph (module-level and
  function-level imports alike; an import inside ``if TYPE_CHECKING:`` does not count);
- ``package_cycles``: the same between sub-packages and top-level modules (``hexacnc.daemon`` and
  ``hexacnc.sim``, say);
- ``long_functions``: functions (methods, nested functions) longer than ``--max-function-lines``;
- ``long_modules``: modules longer than ``--max-module-lines``;
- ``private_cross_package``: ``from a.b import _name`` where ``_name`` is private to another package
  (a module's own package and its sub-packages may share private names, nobody else);
- ``layer_violations``: imports that break the layers (``drivers`` importing ``hexacnc``; the core
  (``hexacnc`` outside ``daemon``, ``commands``, ``bench``) importing the daemon; the simulator
  importing the daemon).
"""
from __future__ import annotations

import argparse
import ast
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

HELP = "architecture figures: import cycles, long functions/modules, private and layer-crossing imports"

PACKAGES = ("hexacnc", "drivers")

#: (importer prefix, imported prefix, reason): an import from the first into the second is a violation
LAYER_RULES: tuple[tuple[str, str, str], ...] = (
    ("drivers", "hexacnc", "the drive layer depends on nothing in hexacnc"),
    ("hexacnc.sim", "hexacnc.daemon", "the simulator never imports the daemon"),
)
#: hexacnc modules that form the core: they never import the daemon, the commands or the benchmarks
CORE_EXCLUDE = ("hexacnc.daemon", "hexacnc.commands", "hexacnc.bench", "hexacnc.cli", "hexacnc.__main__")


@dataclass
class Module:
    name: str
    path: Path
    lines: int
    imports: list[tuple[str, int]] = field(default_factory=list)        # (module, line)
    private: list[tuple[str, str, int]] = field(default_factory=list)   # (module, name, line)
    functions: list[tuple[str, int, int]] = field(default_factory=list)  # (qualname, line, length)


def _module_name(root: Path, path: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(mod: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    pkg = mod.name.split(".")
    if not mod.path.name == "__init__.py":
        pkg = pkg[:-1]
    pkg = pkg[: len(pkg) - (node.level - 1)]
    return ".".join(pkg + ([node.module] if node.module else []))


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


class _Visitor(ast.NodeVisitor):
    def __init__(self, mod: Module, known: set[str]):
        self.mod, self.known, self.stack = mod, known, []

    def visit_If(self, node: ast.If) -> None:
        if _is_type_checking(node):
            for n in node.orelse:
                self.visit(n)
            return
        self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for a in node.names:
            self.mod.imports.append((a.name, node.lineno))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        base = _resolve(self.mod, node)
        for a in node.names:
            full = f"{base}.{a.name}"
            target = full if full in self.known else base
            self.mod.imports.append((target, node.lineno))
            if a.name.startswith("_") and not a.name.startswith("__") and target == base:
                self.mod.private.append((base, a.name, node.lineno))

    def _func(self, node) -> None:
        self.stack.append(node.name)
        length = (node.end_lineno or node.lineno) - node.lineno + 1
        self.mod.functions.append((".".join(self.stack), node.lineno, length))
        self.generic_visit(node)
        self.stack.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = _func

    def visit_ClassDef(self, node: ast.ClassDef) -> None:
        self.stack.append(node.name)
        self.generic_visit(node)
        self.stack.pop()


def scan(root: Path) -> dict[str, Module]:
    """Every module of :data:`PACKAGES` below ``root`` -> parsed :class:`Module`."""
    paths = [p for pkg in PACKAGES for p in sorted((root / pkg).rglob("*.py"))]
    mods = {}
    for p in paths:
        text = p.read_text(encoding="utf-8")
        m = Module(_module_name(root, p), p, text.count("\n") + (not text.endswith("\n")))
        mods[m.name] = (m, text)
    known = set(mods)
    out = {}
    for name, (m, text) in mods.items():
        _Visitor(m, known).visit(ast.parse(text, filename=str(m.path)))
        m.imports = [(_owner(t, known), ln) for t, ln in m.imports]
        m.imports = [(t, ln) for t, ln in m.imports if t and t != name]
        out[name] = m
    return out


def _owner(target: str, known: set[str]) -> str:
    while target and target not in known:
        target = target.rpartition(".")[0]
    return target


def _package(name: str, mods: dict[str, Module]) -> str:
    m = mods[name]
    return name if m.path.name == "__init__.py" else name.rpartition(".")[0]


def import_cycles(mods: dict[str, Module]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    graph = {n: sorted({t for t, _ in m.imports if t in mods}) for n, m in mods.items()}
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = counter[0]
        counter[0] += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(graph[w])))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return sorted(out)


def _unit(name: str) -> str:
    """The layer unit of a module: its sub-package (``hexacnc.daemon``) or itself (``hexacnc.config``)."""
    parts = name.split(".")
    return ".".join(parts[:2])


def package_cycles(mods: dict[str, Module]) -> list[list[str]]:
    """Import cycles between sub-packages and top-level modules (e.g. the daemon and the simulator)."""
    units: dict[str, Module] = {}
    for n, m in mods.items():
        u = units.setdefault(_unit(n), Module(_unit(n), m.path, 0))
        u.imports.extend((_unit(t), ln) for t, ln in m.imports if _unit(t) != _unit(n))
    return import_cycles(units)


def private_cross_package(mods: dict[str, Module]) -> list[dict]:
    out = []
    for name, m in mods.items():
        own = _package(name, mods)
        for target, pname, line in m.private:
            tpkg = _package(target, mods) if target in mods else target.rpartition(".")[0]
            if not (own == tpkg or own.startswith(tpkg + ".")):
                out.append({"module": name, "line": line, "imports": f"{target}.{pname}"})
    return out


def layer_violations(mods: dict[str, Module]) -> list[dict]:
    out = []
    for name, m in mods.items():
        core = name.startswith("hexacnc") and not name.startswith(CORE_EXCLUDE)
        for target, line in m.imports:
            why = "the core never imports the daemon" if core and _under(target, "hexacnc.daemon") else None
            for src, dst, reason in LAYER_RULES:      # the more specific rule names the violation
                if _under(name, src) and _under(target, dst):
                    why = reason
            if why:
                out.append({"module": name, "line": line, "imports": target, "rule": why})
    return out


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def measure(root: Path, max_function_lines: int = 100, max_module_lines: int = 600) -> dict:
    mods = scan(root)
    funcs = [{"function": f"{n}:{q}", "line": ln, "lines": length}
             for n, m in mods.items() for q, ln, length in m.functions if length > max_function_lines]
    big = [{"module": n, "lines": m.lines} for n, m in mods.items() if m.lines > max_module_lines]
    cycles = import_cycles(mods)
    pcycles = package_cycles(mods)
    priv = private_cross_package(mods)
    layers = layer_violations(mods)
    return {
        "modules": len(mods),
        "lines": sum(m.lines for m in mods.values()),
        "mean_module_lines": round(sum(m.lines for m in mods.values()) / max(len(mods), 1), 1),
        "import_cycles": cycles,
        "package_cycles": pcycles,
        "long_functions": sorted(funcs, key=lambda f: -f["lines"]),
        "long_modules": sorted(big, key=lambda b: -b["lines"]),
        "private_cross_package": priv,
        "layer_violations": layers,
        "summary": {"import_cycles": len(cycles), "package_cycles": len(pcycles), "functions_over_limit": len(funcs),
                    "modules_over_limit": len(big), "private_cross_package": len(priv),
                    "layer_violations": len(layers)},
    }


def source_root() -> Path:
    """The folder holding the ``hexacnc`` and ``drivers`` packages being run."""
    return Path(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", default=None, help="folder holding hexacnc/ and drivers/ (default: this install)")
    parser.add_argument("--max-function-lines", type=int, default=100)
    parser.add_argument("--max-module-lines", type=int, default=600)


def main(args: argparse.Namespace) -> int:
    root = Path(args.root) if args.root else source_root()
    print(json.dumps(measure(root, args.max_function_lines, args.max_module_lines), indent=2))
    return 0
