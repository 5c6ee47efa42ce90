"""The package's layers (docs in each folder's ``__init__``): a module may
import its own folder and the folders below it, never one above. Imports
inside ``if __name__ == "__main__":`` (a process's entry point) are exempt."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "diskf_mesh"

# bottom to top; a layer may import every layer listed before it
LAYERS = ["core", "estimators", "data", "engine", "mesh", "studies", "recording", "live", "cli", "api"]
APPS = {"agents", "sim"}  # the processes: may import the whole package, never each other's internals
# the mesh layer's rooms, bottom to top; a room may import every room listed before it
MESH_ROOMS = ["wire", "security", "protocol", "process", "simulated"]


def _layer(path: Path) -> str:
    rel = path.relative_to(ROOT).parts
    if rel[0] in APPS:
        return rel[0]
    return rel[1] if len(rel) > 2 else "root"


def _main_block(node) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and getattr(node.test.left, "id", None) == "__name__")


def _imports(path: Path):
    tree = ast.parse(path.read_text())
    skip = {id(n) for top in tree.body if _main_block(top) for n in ast.walk(top)}
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path.relative_to(ROOT)}:{node.lineno}: relative import"
            mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        else:
            continue
        for m in mods:
            yield node.lineno, m


def _target(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] in APPS:
        return parts[0]
    if parts[0] != "diskf_mesh":
        return None
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "root"


FILES = sorted([*PACKAGE.rglob("*.py"), *(ROOT / "agents").rglob("*.py"), *(ROOT / "sim").rglob("*.py")])


def test_every_folder_is_a_layer():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders == set(LAYERS)
    for name in LAYERS:  # each says what lives there and what it may import
        assert "May import" in (PACKAGE / name / "__init__.py").read_text(), name
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"]


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_down(path):
    here = _layer(path)
    bad = []
    for line, module in _imports(path):
        there = _target(module)
        if there is None or there == "root" or there == here:
            continue
        if here in APPS:
            ok = there not in APPS
        elif here == "root":  # the package's __init__: only the API it re-exports, and the errors it raises
            ok = there in ("api", "core")
        else:
            ok = there not in APPS and LAYERS.index(there) < LAYERS.index(here)
        if not ok:
            bad.append(f"{path.relative_to(ROOT)}:{line}: {here} imports {module}")
    assert not bad, "\n".join(bad)


def _room(module_or_path: str) -> str | None:
    parts = module_or_path.split(".")
    if parts[:2] != ["diskf_mesh", "mesh"] or len(parts) < 3:
        return None
    return parts[2] if parts[2] in MESH_ROOMS else "mesh"


def test_mesh_is_rooms():
    mesh = PACKAGE / "mesh"
    rooms = {p.name for p in mesh.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert rooms == set(MESH_ROOMS)
    assert sorted(p.name for p in mesh.glob("*.py")) == ["__init__.py"]
    for name in MESH_ROOMS:
        assert "May import" in (mesh / name / "__init__.py").read_text(), name


@pytest.mark.parametrize("path", sorted((PACKAGE / "mesh").rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT)))
def test_mesh_rooms_point_down(path):
    here = _room(".".join(path.relative_to(ROOT).with_suffix("").parts))
    bad = []
    for line, module in _imports(path):
        there = _room(module)
        if there is None or there == "mesh" or here == "mesh" or there == here:
            continue
        if MESH_ROOMS.index(there) > MESH_ROOMS.index(here):
            bad.append(f"{path.relative_to(ROOT)}:{line}: mesh.{here} imports {module}")
    assert not bad, "\n".join(bad)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict:
    """Module -> the project modules it imports (anywhere in it but its
    ``__main__`` block, ``importlib.import_module("name")`` included); a
    package's ``__init__`` is not a target (a submodule reaches its package's
    namespace without a circle of modules)."""
    modules = {_module_name(p): p for p in FILES}
    graph = {}
    for name, path in modules.items():
        found = {m for _, m in _imports(path)}
        tree = ast.parse(path.read_text())
        skip = {id(n) for top in tree.body if _main_block(top) for n in ast.walk(top)}
        found |= {n.args[0].value for n in ast.walk(tree) if id(n) not in skip and isinstance(n, ast.Call)
                  and getattr(n.func, "attr", None) == "import_module" and n.args
                  and isinstance(n.args[0], ast.Constant)}
        graph[name] = {m for m in found if m in modules and m != name and modules[m].name != "__init__.py"}
    return graph


def circles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on.discard(component[-1])
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_circles_are_found():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    """No module reaches itself again through the modules it imports."""
    assert circles(_import_graph()) == []
