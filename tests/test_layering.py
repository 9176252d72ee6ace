"""The package's import graph has no cycles among e3dpsm modules.

Rule: an edge A -> B for every import A executes when it is imported: import statements at
module level, in class bodies and under module-level `if` / `try`, but not inside
functions (a deferred import runs after every module involved has finished loading, which
is how optional and heavy dependencies are kept out of the torch-free paths) and not under
`if TYPE_CHECKING:` (never executed). `from X import Y` is an edge to X, and to X.Y when
that is a module. Importing X.Y also runs the package X's `__init__`: that is an edge to X
too, unless the importer lives inside X (its own package is already loading). Parsed with
ast, nothing imported, so the test sees every module, torch-only ones included.
"""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Cycles known and owned elsewhere; each entry is a sorted tuple of the modules of one
# strongly connected component. A cycle not listed here fails the test.
KNOWN_CYCLES: set[tuple[str, ...]] = set()


def package_modules() -> dict[str, Path]:
    """Module name -> file, from the package-dir mapping of pyproject.toml (e3dpsm.export
    lives in export/, and so on)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    package_dir: dict[str, str] = config["tool"]["setuptools"]["package-dir"]
    modules: dict[str, Path] = {}
    for package, folder in package_dir.items():
        base = ROOT / folder
        for path in base.rglob("*.py"):
            parts = path.relative_to(base).with_suffix("").parts
            if any(not p.isidentifier() for p in parts):
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join((package, *parts))
            modules.setdefault(name, path)  # e3dpsm/export/ would lose to export/; there is none
    return modules


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level_imports(tree: ast.Module, *, type_checking: bool = False) -> list[ast.Import | ast.ImportFrom]:
    """The imports run at import time; with `type_checking`, also those under `if TYPE_CHECKING:`."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                found.append(node)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            elif isinstance(node, ast.If):
                if type_checking or not _type_checking(node.test):
                    visit(node.body)
                visit(node.orelse)
            else:
                for field in ("body", "orelse", "finalbody", "handlers"):
                    block = getattr(node, field, None)
                    if isinstance(block, list):
                        visit([b for b in block if isinstance(b, ast.stmt)] if field != "handlers"
                              else [s for h in block for s in h.body])

    visit(tree.body)
    return found


def import_edges(modules: dict[str, Path], *, type_checking: bool = False) -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        package = name if is_package else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in _module_level_imports(ast.parse(path.read_text(), str(path)), type_checking=type_checking):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
                continue
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            targets.add(base)
            targets.update(f"{base}.{alias.name}" for alias in node.names)
        own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1 + is_package)}
        for target in targets:
            parts = target.split(".")
            for i in range(1, len(parts) + 1):  # the target and every package above it
                candidate = ".".join(parts[:i])
                if candidate in modules and candidate not in own and candidate != name:
                    edges[name].add(candidate)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[tuple[str, ...]] = []
    counter = 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(tuple(sorted(component)))
    return found


def test_the_walk_sees_the_whole_package():
    modules = package_modules()
    for name in ("e3dpsm.runtime.session", "e3dpsm.export.parity", "e3dpsm.quantize.pipeline", "e3dpsm.profiles.flops",
                 "e3dpsm.golden.diagnose", "e3dpsm.onnx_groups", "e3dpsm.cli"):
        assert name in modules, name
    edges = import_edges(modules)
    assert "e3dpsm.runtime.stepping" in edges["e3dpsm.runtime.session"]
    assert "e3dpsm.export.torch_stepper" in edges["e3dpsm.export.parity"]


def test_cycle_finder_finds_a_planted_cycle():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(edges) == [("a", "b", "c")]


def test_no_import_cycles_among_package_modules():
    found = set(cycles(import_edges(package_modules())))
    assert not found - KNOWN_CYCLES, f"import cycles: {sorted(found - KNOWN_CYCLES)}"


def test_serve_has_no_import_cycle_even_in_its_type_annotations():
    """Stricter inside e3dpsm.serve: the modules form layers (protocol and the shared stats
    below clients, clients below the estimator and the report, all below the app and the
    server), so not even an import kept for type checkers may point back up."""
    serve = {name: path for name, path in package_modules().items() if name.startswith("e3dpsm.serve")}
    edges = import_edges(serve, type_checking=True)
    assert "e3dpsm.serve.clients" in edges["e3dpsm.serve.report"]  # a TYPE_CHECKING import is seen
    assert cycles(edges) == []


def _imported_names(tree: ast.Module, package: str) -> set[str]:
    """Every module an import anywhere in the file names (inside functions too), relative ones resolved."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            anchor = package.split(".")[: len(package.split(".")) - max(node.level - 1, 0)] if node.level else []
            base = ".".join([*anchor, node.module] if node.module else anchor)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def test_the_library_never_imports_the_cli():
    """The CLI parses and delegates: no module outside e3dpsm.cli reaches into it, not even from
    inside a function (the entry point `e3dpsm.__main__` excepted)."""
    offenders = []
    for name, path in package_modules().items():
        if name == "e3dpsm.cli" or name.startswith("e3dpsm.cli.") or name == "e3dpsm.__main__":
            continue
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        imported = _imported_names(ast.parse(path.read_text(), str(path)), package)
        offenders += [f"{name} -> {target}" for target in sorted(imported)
                      if target == "e3dpsm.cli" or target.startswith("e3dpsm.cli.")]
    assert offenders == [], offenders
