"""The package's shape: imports go down the layers, none in a circle; small modules; all documented.

Layers (a module may import its own package and anything in a lower layer, nothing else):

0. the shared core (``jaxloc/*.py``) and ``jaxloc.raycasting``
1. the methods, ``jaxloc.sg2loc`` and ``jaxloc.m2loc`` (neither imports the other)
2. ``jaxloc.io`` (real formats, map files) and ``jaxloc.synthetic`` (neither imports the other)
3. ``jaxloc.mapping`` (maps from recordings: reads with io, builds the methods' types)
4. ``jaxloc.cli``

Every import counts: module level, inside functions and under ``TYPE_CHECKING``. The root package
``jaxloc`` (the public facade) is imported by no module of the library.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "jaxloc"
LAYERS = {"core": 0, "raycasting": 0, "sg2loc": 1, "m2loc": 1, "io": 2, "synthetic": 2}
LAYERS |= {"mapping": 3, "cli": 4}
#: Longest module in lines (split by responsibility well before this).
MAX_LINES = 500


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def group(module: str) -> str:
    """The package a module belongs to for layering: its first component below ``jaxloc``, or
    "core" for the top-level modules."""
    parts = module.split(".")
    if len(parts) == 1:
        return "root"
    if len(parts) == 2 and not (ROOT / parts[1]).is_dir():
        return "core"
    return parts[1]


def imports_of(module: str) -> set[str]:
    """The jaxloc modules ``module`` imports (``from pkg import sub`` counts as ``pkg.sub``)."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: up level - 1 packages from this module's package
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            subs = [f"{base}.{alias.name}" for alias in node.names]
            names = [s for s in subs if s in MODULES] or [base]
        else:
            continue
        for name in names:
            while name and name not in MODULES:
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
    found.discard(module)
    return found


GRAPH = {module: imports_of(module) for module in MODULES}


def test_every_import_goes_down_the_layers():
    wrong = []
    for module, targets in GRAPH.items():
        source = group(module)
        if source == "root":
            continue
        for target in targets:
            kind = group(target)
            if kind == "root":
                ok = False
            elif kind == source or {kind, source} <= {"core", "raycasting"}:
                ok = True
            else:
                ok = LAYERS[kind] < LAYERS[source]
            if not ok:
                wrong.append(f"{module} -> {target}")
    assert not wrong, "imports against the layers:\n" + "\n".join(sorted(wrong))


def test_no_module_imports_in_a_circle():
    """Tarjan's strongly connected components of the module graph: all of size one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in GRAPH[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in GRAPH:
        if node not in index:
            visit(node)
    assert not cycles, f"import cycles: {cycles}"


def test_the_checks_see_a_bad_import(monkeypatch):
    """The two checks above fail on an upward import and on a circle (so they are not vacuous)."""
    monkeypatch.setitem(
        GRAPH, "jaxloc.m2loc._matching", GRAPH["jaxloc.m2loc._matching"] | {"jaxloc.io"}
    )
    with pytest.raises(AssertionError, match="m2loc._matching -> jaxloc.io"):
        test_every_import_goes_down_the_layers()
    monkeypatch.setitem(GRAPH, "jaxloc.geometry", GRAPH["jaxloc.geometry"] | {"jaxloc.camera"})
    monkeypatch.setitem(GRAPH, "jaxloc.camera", GRAPH["jaxloc.camera"] | {"jaxloc.geometry"})
    with pytest.raises(AssertionError, match="import cycles"):
        test_no_module_imports_in_a_circle()


def test_every_package_and_module_is_known_and_small():
    assert {group(m) for m in MODULES} - {"root"} == set(LAYERS)
    long = {m: n for m, p in MODULES.items() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_every_public_module_is_in_the_api_reference():
    """Each module without a private component is rendered by a ``::: module`` line of the docs'
    API pages (``mkdocs build --strict`` then fails on any broken reference inside them)."""
    pages = (ROOT.parent / "docs" / "pages" / "api").glob("*.md")
    lines = [line for p in pages for line in p.read_text().splitlines()]
    rendered = {line[4:].strip() for line in lines if line.startswith("::: ")}
    public = {m for m in MODULES if not any(part.startswith("_") for part in m.split("."))}
    assert public - rendered == set()


def test_the_version_lives_in_pyproject_only():
    """``jaxloc.__version__`` is the installed metadata of pyproject's version, and no module
    writes a version string of its own."""
    import tomllib

    import jaxloc

    pyproject = tomllib.loads((ROOT.parent / "pyproject.toml").read_text())
    assert jaxloc.__version__ == pyproject["project"]["version"]
    own = [m for m, p in MODULES.items() if "__version__ =" in p.read_text() and m != "jaxloc"]
    assert not own


REEXPORTING = [
    m for m, p in MODULES.items() if p.name == "__init__.py" and "public_names" in p.read_text()
]


def test_the_re_exporting_packages_are_these():
    assert set(REEXPORTING) == {
        "jaxloc",
        "jaxloc.io",
        "jaxloc.m2loc",
        "jaxloc.mapping",
        "jaxloc.raycasting",
        "jaxloc.sg2loc",
        "jaxloc.sg2loc.learn",
        "jaxloc.sg2loc.refine",
        "jaxloc.synthetic.indoor",
    }


@pytest.mark.parametrize("package", REEXPORTING)
def test_a_package_lists_each_public_name_once(package):
    """A package that re-exports lists each public name once, as a redundant-alias import
    (``from module import name as name``; under ``if TYPE_CHECKING:`` when it is imported on first
    use, jaxloc._lazy): ``__all__`` is derived from those imports, never written as a list, every
    name resolves to the object its import names, and no other import is public."""
    import importlib

    module = importlib.import_module(package)
    tree = ast.parse(MODULES[package].read_text())
    assigned = [n for n in tree.body if isinstance(n, ast.Assign) and "__all__" in ast.unparse(n)]
    assert len(assigned) == 1 and "public_names(__file__)" in ast.unparse(assigned[0].value)
    imported = []
    for node in tree.body:
        body = node.body if isinstance(node, ast.If) else [node]
        for stmt in body:
            if isinstance(stmt, ast.ImportFrom) and stmt.module not in ("__future__", "typing"):
                for alias in stmt.names:
                    name = alias.asname or alias.name
                    assert (
                        alias.asname == alias.name
                        or name.startswith("_")
                        or name
                        in (
                            "lazy_exports",
                            "public_names",
                            "renamed_modules",
                            "deprecated_names",
                            "version",
                            "PackageNotFoundError",
                        )
                    ), f"{package}: {name} is imported but not public"
                    if alias.asname == alias.name:
                        imported.append(name)
                        target = importlib.import_module(stmt.module)
                        expected = getattr(target, alias.name, None)
                        if expected is None:  # ``from package import submodule as submodule``
                            expected = importlib.import_module(f"{stmt.module}.{alias.name}")
                        assert getattr(module, name) is expected, name
    assert [name for name in module.__all__ if name != "__version__"] == imported
