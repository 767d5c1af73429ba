"""The package's import structure: layers from the bottom (units, config, sim) to the top (cli), no circles.

Imports are read from the source with ``ast`` (module-level and function-local ones, and those under
``TYPE_CHECKING``), so the check sees every dependency a reader sees, whether or not it runs at import time.
The layers are those of docs/architecture.md; a module may import from its own layer or below.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cv2x_marl

ROOT = Path(cv2x_marl.__file__).parent

#: bottom (0) to top; the first matching prefix decides (longest prefixes first)
LAYERS: dict[str, int] = {
    "cv2x_marl.units": 0,
    "cv2x_marl.checks": 0,
    "cv2x_marl.io": 0,
    "cv2x_marl.rng": 0,
    "cv2x_marl.yamlcore": 0,
    "cv2x_marl.extras": 0,
    "cv2x_marl.runs": 0,
    "cv2x_marl.run_manifest": 0,
    "cv2x_marl.interrupts": 0,
    "cv2x_marl.plotting": 0,
    "cv2x_marl.parallel": 0,
    "cv2x_marl.utility": 0,
    "cv2x_marl.schema": 0,
    "cv2x_marl.stats": 0,
    "cv2x_marl.docstrings": 0,
    "cv2x_marl.config": 1,
    "cv2x_marl.config_sections": 1,
    "cv2x_marl.sim": 2,
    "cv2x_marl.regression": 3,
    "cv2x_marl.env": 4,
    "cv2x_marl.policies": 5,
    "cv2x_marl.validation": 6,
    "cv2x_marl.experiments": 6,
    "cv2x_marl.rl": 7,
    "cv2x_marl.cli": 8,
    "cv2x_marl.__main__": 8,
    "cv2x_marl": 8,  # the package's face (registration by import strings)
}

#: bottom to top inside sim/: the kernels import nothing else of sim
SIM_KERNELS = "cv2x_marl.sim.kernels"


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer(module: str) -> int:
    for prefix in sorted(LAYERS, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return LAYERS[prefix]
    raise AssertionError(f"{module} is in no layer of tests/test_layers.py")


def package_imports(path: Path, modules: set[str]) -> set[str]:
    """The modules of the package that ``path`` imports (``from a.b import c`` counts ``a.b.c`` when that is a
    module, else ``a.b``)."""
    name = module_name(path)
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def import_graph() -> dict[str, set[str]]:
    files = sorted(ROOT.rglob("*.py"))
    modules = {module_name(f) for f in files}
    return {module_name(f): package_imports(f, modules) for f in files}


def test_every_module_is_in_a_layer() -> None:
    for module in import_graph():
        layer(module)


def test_no_import_runs_up_the_layers() -> None:
    upward = [
        f"{a} (layer {layer(a)}) imports {b} (layer {layer(b)})"
        for a, targets in import_graph().items()
        for b in sorted(targets)
        if layer(b) > layer(a) and "cv2x_marl" not in (a, b)
    ]
    assert upward == []


def test_the_package_root_imports_only_the_registry() -> None:
    """``cv2x_marl/__init__.py`` carries ``__version__`` (which any layer may read) and registers the env ids
    through :mod:`cv2x_marl.env.registry`, whose top imports only the standard library and the defaults table
    (:mod:`cv2x_marl.env.defaults`, plain data importing nothing of the package), so reading the version from
    below is no upward dependency."""
    assert import_graph()["cv2x_marl"] == {"cv2x_marl.env.registry"}
    for name, allowed in (("registry.py", ["cv2x_marl.env.defaults"]), ("defaults.py", [])):
        tree = ast.parse((ROOT / "env" / name).read_text(encoding="utf-8"))
        top = [n for n in tree.body if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("cv2x_marl")]
        assert [n.module for n in top] == allowed, name


def test_the_kernels_import_nothing_else_of_sim() -> None:
    bad = [
        f"{a} imports {b}"
        for a, targets in import_graph().items()
        if a.startswith(SIM_KERNELS)
        for b in targets
        if b.startswith("cv2x_marl.sim") and not b.startswith(SIM_KERNELS)
    ]
    assert bad == []


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm: the components of more than one module (the import circles)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_circle_finder_finds_a_hand_made_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert strongly_connected(graph) == [["a", "b", "c"]]


def test_no_import_circles() -> None:
    graph = import_graph()
    # a package's __init__ that re-exports its modules is its face, not a participant
    faces = {m for m in graph if (ROOT.parent / m.replace(".", "/") / "__init__.py").exists()}
    inner = {a: {b for b in targets if b not in faces} for a, targets in graph.items() if a not in faces}
    assert strongly_connected(inner) == []


def test_no_module_over_800_lines() -> None:
    long = {
        module_name(f): n for f in ROOT.rglob("*.py") if (n := len(f.read_text(encoding="utf-8").splitlines())) > 800
    }
    assert long == {}
