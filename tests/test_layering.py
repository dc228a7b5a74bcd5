"""The packages' import graph: no circles between files, arrows pointing down only.

Every module of apcg_core, dataset_builder, training and blender_addon is parsed (not imported)
and every import statement in it is an arrow, those inside functions included: a circle hidden
in a function-level import is still two files that need each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("apcg_core", "dataset_builder", "training", "blender_addon")
# package -> the packages it must never import (DESIGN.md, "Layout")
BELOW_ONLY = {"apcg_core": {"dataset_builder", "training", "blender_addon"},
              "dataset_builder": {"training", "blender_addon"},
              "training": {"blender_addon"}}


def modules(root: Path, packages) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of ``packages`` under ``root``."""
    out = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = f
    return out


def _known(name: str, mods) -> str | None:
    """``name`` if it is one of ``mods``, else its nearest enclosing module that is."""
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, mods) -> set[str]:
    """The modules of ``mods`` that module ``name`` imports, anywhere in its file."""
    is_pkg = path.name == "__init__.py"
    here = name if is_pkg else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.split(".")
                base = base[:len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            # `from pkg import sub` imports the module pkg.sub; `from mod import name`, mod
            targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src
                       for a in node.names]
        else:
            continue
        for t in targets:
            k = _known(t, mods)
            if k and k != name:
                out.add(k)
    return out


def import_graph(root: Path = ROOT, packages=PACKAGES) -> dict[str, set[str]]:
    mods = modules(root, packages)
    return {m: imports_of(m, f, mods) for m, f in mods.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out = []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def upward(graph: dict[str, set[str]]) -> list[str]:
    """Every arrow from a package to one it must never import, as 'a -> b'."""
    return sorted(f"{a} -> {b}" for a, targets in graph.items() for b in targets
                  if b.split(".")[0] in BELOW_ONLY.get(a.split(".")[0], ()))


def test_no_import_circles_between_files():
    found = cycles(import_graph())
    assert not found, "modules that import each other (a function-level import counts): " + \
        "; ".join(" <-> ".join(c) for c in found)


def test_arrows_point_down_only():
    found = upward(import_graph())
    assert not found, "imports against the layering (DESIGN.md, Layout): " + "; ".join(found)


def test_the_graph_sees_every_package_and_the_families():
    g = import_graph()
    assert {m.split(".")[0] for m in g} == set(PACKAGES)
    # a function-level import is an arrow (training.families.cgan imports export in a method)
    assert "training.export" in g["training.families.cgan"]
    assert "apcg_core.families.base" in g["apcg_core.families.cgan"]


def _tree(tmp_path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_the_checks_find_a_function_level_circle_and_an_upward_arrow(tmp_path):
    root = _tree(tmp_path, {
        "apcg_core/__init__.py": "",
        "apcg_core/a.py": "def f():\n    from . import b\n",
        "apcg_core/b.py": "from .a import f\n",
        "apcg_core/pkg/__init__.py": "",
        "apcg_core/pkg/c.py": "def g():\n    from ..a import f\n    import training.t\n",
        "training/__init__.py": "",
        "training/t.py": "from apcg_core.pkg import c\n",
    })
    g = import_graph(root, ("apcg_core", "training"))
    assert g["apcg_core.pkg.c"] == {"apcg_core.a", "training.t"}
    assert g["training.t"] == {"apcg_core.pkg.c"}
    assert cycles(g) == [["apcg_core.a", "apcg_core.b"], ["apcg_core.pkg.c", "training.t"]]
    assert upward(g) == ["apcg_core.pkg.c -> training.t"]
