"""Layout: no two harness modules import each other (one place chooses the executor), no compatibility layer."""

import ast
from pathlib import Path

HARNESS = Path(__file__).resolve().parents[1] / "harness"


def import_graph() -> dict[str, set[str]]:
    """module -> harness modules it imports anywhere in its file (top level or inside functions)."""
    modules = {}
    for path in HARNESS.rglob("*.py"):
        parts = path.relative_to(HARNESS.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                targets = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def test_no_two_modules_import_each_other():
    graph = import_graph()
    assert "harness.run.ray_executor" not in graph["harness.run.workers"]
    pairs = sorted((a, b) for a in graph for b in graph[a] if a in graph[b] and a < b
                   and not b.startswith(a + ".") and not a.startswith(b + "."))  # a package and its own modules
    assert pairs == []


def test_one_place_chooses_the_executor_and_no_compatibility_layer():
    graph = import_graph()
    choosers = sorted(m for m in graph if {"harness.run.workers", "harness.run.ray_executor"} <= graph[m])
    assert choosers == ["harness.run.execution"]
    assert not (HARNESS / "runner.py").exists()
    benchmarks = "".join(p.read_text() for p in (HARNESS.parent / "benchmarks").glob("*.py"))
    assert "harness.runner" not in benchmarks and "RunConfig" not in benchmarks


def test_every_module_imports_and_states_its_job():
    """The quick subset (`pytest -m "not slow"`) imports every module of harness/ and envs/ here, so none is left
    out of it; each module's docstring states its job."""
    import importlib

    root = HARNESS.parent
    names = sorted(".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
                   for package in ("harness", "envs") for p in (root / package).rglob("*.py"))
    undocumented = [name for name in names if not (importlib.import_module(name).__doc__ or "").strip()]
    assert len(names) > 60 and undocumented == []
