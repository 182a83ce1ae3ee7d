"""The dependency picture flows one way: cli -> driver -> stages -> kernels, with no import
circles among the package's modules (imports inside functions count too)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (("warpgauss", "warpgauss"), ("cli", "warpgauss.cli"), ("kernels", "warpgauss.kernels"))


def _imports() -> dict[str, set[str]]:
    """Module -> the package modules it imports (``from . import x`` counts as ``x``)."""
    mods: dict[str, set[str]] = {}
    for folder, pkg in PACKAGES:
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            name = ".".join((pkg, *parts)).removesuffix(".__init__")
            deps: set[str] = set()
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom):
                    if node.level:
                        base = name.split(".")
                        if path.name != "__init__.py":
                            base = base[:-1]
                        base = base[: len(base) - (node.level - 1)]
                        mod = ".".join(base + ([node.module] if node.module else []))
                    else:
                        mod = node.module or ""
                    subs = {f"{mod}.{a.name}" for a in node.names}
                    deps |= subs if not node.module and node.level else {mod} | subs
                elif isinstance(node, ast.Import):
                    deps |= {a.name for a in node.names}
            mods[name] = deps
    return {m: {d for d in deps if d in mods and d != m} for m, deps in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circles():
    assert _cycles(_imports()) == []


def test_dependencies_flow_one_way():
    graph = _imports()
    for mod, deps in graph.items():
        for dep in deps:
            if mod.startswith("warpgauss.kernels"):
                assert dep.startswith("warpgauss.kernels"), f"{mod} (a kernel module) imports {dep}"
            if not mod.startswith("warpgauss.cli"):
                assert not dep.startswith("warpgauss.cli"), f"{mod} imports the CLI ({dep})"


def test_the_circle_finder_finds_circles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# The package's floors, lowest first: a module imports only from its own floor and those below.
FLOORS = (
    ("warpgauss.errors", "warpgauss._version"),
    ("warpgauss.core",),
    ("warpgauss.readers",),
    ("warpgauss.field",),
    ("warpgauss.format",),
    ("warpgauss.encoding",),
    ("warpgauss.series",),
    ("warpgauss.render",),
    ("warpgauss.codec", "warpgauss.paraview", "warpgauss"),
)


def _floor(mod: str) -> int | None:
    best = None
    for i, prefixes in enumerate(FLOORS):
        for p in prefixes:
            if (mod == p or mod.startswith(p + ".")) and (best is None or len(p) > best[1]):
                best = (i, len(p))
    return None if best is None else best[0]


def test_nothing_imports_upward():
    graph = _imports()
    up = []
    for mod, deps in graph.items():
        if not mod.startswith("warpgauss") or mod.startswith(("warpgauss.cli", "warpgauss.kernels")):
            continue
        for dep in deps:
            if dep.startswith(("warpgauss.cli", "warpgauss.kernels")) or _floor(dep) is None:
                continue
            if _floor(dep) > _floor(mod) and not (mod == "warpgauss" or mod.startswith("warpgauss.paraview")):
                up.append(f"{mod} -> {dep}")
    assert up == []


def test_the_whole_volume_path_imports_no_bricking_module():
    """encode decides once (encoding.entry); the whole-volume driver and the stages never reach
    into scale/ (imports inside functions count)."""
    graph = _imports()
    seen, todo = set(), ["warpgauss.encoding.driver.run", "warpgauss.encoding.driver.load", "warpgauss.encoding.driver.bounded"]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo += [d for d in graph.get(m, ()) if d.startswith("warpgauss.")]
    assert not {m for m in seen if m.startswith("warpgauss.encoding.scale")}
    assert "warpgauss.encoding.scale.driver" in graph["warpgauss.encoding.entry"]


def test_the_top_of_the_package_is_a_few_rooms_and_no_module_is_long():
    top = sorted(p.name for p in (ROOT / "warpgauss").iterdir() if p.name != "__pycache__" and not p.is_symlink())
    assert len(top) <= 13, top
    for folder in ("warpgauss", "cli", "kernels"):
        for path in (ROOT / folder).rglob("*.py"):
            n = len(path.read_text().splitlines())
            assert n <= 600, f"{path.relative_to(ROOT)}: {n} lines"


def _long_functions(folders: tuple[str, ...], most: int = 120, root: Path = ROOT) -> list[str]:
    """Functions (methods and nested ones too) longer than ``most`` lines, counted from the ``def``
    line to the last line, decorators excluded."""
    long = []
    for folder in folders:
        for path in sorted((root / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = (node.end_lineno or node.lineno) - node.lineno + 1
                    if n > most:
                        long.append(f"{path.relative_to(root)}:{node.lineno} {node.name}: {n} lines")
    return long


def test_no_function_outside_kernels_is_long():
    """Issue #54: no function above 120 lines outside kernels/: the API, the drivers, the command
    line, and the benchmarks, examples and tests beside them."""
    assert _long_functions(("warpgauss", "cli", "benchmarks", "examples", "tests")) == []


def test_the_long_function_finder_counts_from_def_to_end(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(119))  # with the def line: 120, the decorator not counted
    (tmp_path / "pkg").mkdir()
    method = body.replace("\n", "\n    ")
    (tmp_path / "pkg" / "m.py").write_text(
        f"@staticmethod\ndef ok():\n{body}\n\n\nclass C:\n    def long(self):\n    {method}\n        return 1\n"
    )
    assert _long_functions(("pkg",), root=tmp_path) == ["pkg/m.py:125 long: 121 lines"]
