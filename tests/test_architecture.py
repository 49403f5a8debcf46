"""The layering of the package (README "Architecture"): algorithms know no runtime, the runtime
knows no algorithm, node, source module or algorithm topic, and only stage A's process loads torch."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "neoslam_stream"


def _imports(path: Path) -> set[str]:
    """Every module an import statement of ``path`` names, relative imports resolved."""
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    # the package a relative import starts from: the module's own for __init__.py, else its parent's
    package = ".".join(parts[:-1])
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]  # one level up per extra dot
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.add(target)
            found.update(f"{target}.{a.name}" for a in node.names)
    return found


def _modules(sub: str) -> list[Path]:
    return sorted((PKG / sub).rglob("*.py"))


def _offending(paths: list[Path], forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    bad = {}
    for p in paths:
        hits = sorted(m for m in _imports(p) if any(m == f or m.startswith(f + ".") for f in forbidden))
        if hits:
            bad[str(p.relative_to(PKG.parent))] = hits
    return bad


def test_the_import_scan_sees_relative_imports():
    # the scan itself must be able to fail: a node module imports the runtime and the algorithms
    found = _imports(PKG / "nodes" / "frontend.py")
    assert "neoslam_stream.runtime.node" in found and "neoslam_stream.algorithms.frontend" in found


def test_no_algorithm_module_imports_the_runtime_nodes_or_zenoh():
    paths = _modules("algorithms")
    assert len(paths) >= 10
    forbidden = ("neoslam_stream.runtime", "neoslam_stream.nodes", "neoslam_stream.sources",
                 "neoslam_stream.api", "neoslam_stream.launch", "neoslam_stream.cli", "zenoh", "msgpack")
    assert _offending(paths, forbidden) == {}


def test_the_runtime_imports_no_algorithm_node_or_source():
    paths = _modules("runtime")
    assert len(paths) >= 10
    forbidden = ("neoslam_stream.algorithms", "neoslam_stream.nodes", "neoslam_stream.sources",
                 "neoslam_stream.config", "neoslam_stream.api", "neoslam_stream.launch", "neoslam_stream.cli",
                 "torch")
    assert _offending(paths, forbidden) == {}


def test_the_scan_sees_a_forbidden_import():
    # the check above must be able to fail: launch is where the runtime meets nodes and sources
    found = _offending([PKG / "launch.py"], ("neoslam_stream.sources", "neoslam_stream.nodes"))
    assert found and all(m.startswith(("neoslam_stream.sources", "neoslam_stream.nodes"))
                         for m in found["neoslam_stream/launch.py"])


def _code_strings(path: Path) -> set[str]:
    """The string constants of ``path``'s code (docstrings left out), f-string parts included."""
    tree = ast.parse(path.read_text())
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    return {n.value for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs}


def test_the_runtime_names_no_algorithm_topic():
    # the plan gives the final topic, the capacities and the schemas of the nodes' topics
    from neoslam_stream.nodes.topics import ALGORITHM_TOPICS

    names = {str(t) for t in ALGORITHM_TOPICS}
    assert "experience_map/pose" in names and "pose_cells/action" in names
    assert names <= _code_strings(PKG / "nodes" / "topics.py")  # the scan can see them
    bad = {}
    for p in _modules("runtime"):
        hits = sorted(s for s in _code_strings(p) if any(s == n or s.startswith(n + "/") for n in names))
        if hits:
            bad[str(p.relative_to(PKG.parent))] = hits
    assert bad == {}


def _loaded_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True, timeout=120)
    return set(out.stdout.split())


def test_importing_every_algorithm_loads_no_runtime_and_no_zenoh():
    mods = [".".join(p.relative_to(PKG.parent).with_suffix("").parts) for p in _modules("algorithms")
            if p.name != "__init__.py" and p.name != "backbones.py"]
    loaded = _loaded_after("\n".join(f"import {m}" for m in mods))
    assert "zenoh" not in loaded
    assert not any(m.startswith(("neoslam_stream.runtime", "neoslam_stream.nodes")) for m in loaded)
    assert "torch" not in loaded  # configs and the pure algorithms do not need it


@pytest.mark.parametrize("node", ["frontend", "ratslam", "recorder", "pipelines"])
def test_only_stage_a_loads_torch(node):
    # each worker imports its node's module: only A's setup may bring in torch (~180 MB a process)
    assert "torch" not in _loaded_after(f"import neoslam_stream.nodes.{node}\nimport neoslam_stream.runtime.worker")


def test_stage_a_node_does_load_torch_when_it_builds_its_extractor():
    code = ("from neoslam_stream.nodes.frontend import make_node\n"
            "n = make_node('features', features={'backbone': 'random_alexnet'}); n.setup()")
    assert "torch" in _loaded_after(code)


def _runtime_import_graph() -> dict[str, set[str]]:
    """Runtime module -> the runtime modules it imports, at module level or inside a function."""
    paths = _modules("runtime")
    names = {".".join(p.relative_to(PKG.parent).with_suffix("").parts): p for p in paths}
    return {name: _imports(path) & set(names) - {name} for name, path in names.items()}


def _import_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of ``graph`` as [a, b, ..., a], or [] when it has none (depth-first search)."""
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> list[str]:
        if node in path:
            return path[path.index(node):] + [node]
        if node in done:
            return []
        for nxt in sorted(graph.get(node, ())):
            cycle = visit(nxt, path + [node])
            if cycle:
                return cycle
        done.add(node)
        return []

    for start in sorted(graph):
        cycle = visit(start, [])
        if cycle:
            return cycle
    return []


def test_the_cycle_search_finds_a_cycle():
    # the check below must be able to fail: a loop through a lazy import is one
    assert _import_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _import_cycle({"a": {"b"}, "b": set()}) == []
    graph = _runtime_import_graph()
    assert "neoslam_stream.runtime.worker" in graph["neoslam_stream.runtime.procs"]  # a lazy import is seen


def test_the_runtime_has_no_import_cycle():
    assert _import_cycle(_runtime_import_graph()) == []
