"""Layout: an explicit stage order that no import runs back up, no two harness modules import each other (one place
chooses the executor), no compatibility layer."""

import ast
from pathlib import Path

HARNESS = Path(__file__).resolve().parents[1] / "harness"
ENVS = HARNESS.parent / "envs"

# The data path, lowest stage first. A module may import its own stage and the stages before it, never a later one.
# `measures` (the per-step maths: attention slicing, attribution, deletion fills, the controls' frame transforms,
# region reliance; and the success statistics the run store writes) sits below `policy`, which computes them at a
# step; `runfolder` (a run folder's schema, integrity and platform record) sits below both `run` (which writes run
# folders) and `analysis` (which reads them, offline, above the run store). The gate commands (regress, replay,
# sanity, view, robustness grids) read analysis and run the run store, so they sit above both. `reference` trains
# the reference policies with the closed loop and the statistics; nothing but the command line sits above `report`.
STAGES = (
    ("envs", ("envs",)),
    ("base", ("harness", "harness.files", "harness.console")),
    ("octo", ("harness.octo",)),
    ("measures", ("harness.measures",)),
    ("policy", ("harness.interventions", "harness.policy", "harness.conventions")),
    ("rollout", ("harness.records", "harness.rollout")),
    ("outputs", ("harness.outputs",)),
    ("runfolder", ("harness.runfolder",)),
    ("run", ("harness.run",)),
    ("analysis", ("harness.analysis",)),
    ("gate", ("harness.gate",)),
    ("reference", ("harness.reference",)),
    ("report", ("harness.report",)),
    ("cli", ("harness.cli",)),
)


def stage_of(module: str) -> int:
    """Index in STAGES of the longest prefix naming `module` (a package holds its modules)."""
    best = None
    for index, (_, prefixes) in enumerate(STAGES):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > best[1]):
                best = (index, len(prefix))
    assert best is not None, f"{module} is in no stage of tests/test_layout.py's STAGES; add it where it belongs"
    return best[0]


def import_graph(roots=(HARNESS,)) -> dict[str, set[str]]:
    """module -> harness modules it imports anywhere in its file (top level or inside functions)."""
    modules = {}
    for path in (p for root in roots for p in root.rglob("*.py")):
        parts = path.relative_to(HARNESS.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:  # `from pkg import mod` imports pkg.mod
                names = [f"{node.module}.{a.name}" for a in node.names]
                targets = [n for n in names if n in modules] or [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def test_no_module_imports_a_later_stage():
    graph = import_graph((HARNESS, ENVS))
    assert "harness.runfolder.schema" in graph and "envs" in graph
    upward = sorted(f"{a} ({STAGES[stage_of(a)][0]}) imports {b} ({STAGES[stage_of(b)][0]})"
                    for a in graph for b in graph[a] if stage_of(b) > stage_of(a))
    assert upward == []


def test_the_stage_check_sees_an_upward_import():
    """The check above can fail: the run store reading analysis (which sits above it now), the policy reading
    analysis (what issue 42 moved into measures) or analysis reading a gate command is reported."""
    assert stage_of("harness.measures.attribution") < stage_of("harness.policy") < stage_of("harness.run.store")
    assert stage_of("harness.runfolder.schema") < stage_of("harness.run.store") < stage_of("harness.analysis.runs")
    assert stage_of("harness.analysis.runs") < stage_of("harness.gate.regress") < stage_of("harness.report.build")
    assert [name for name, _ in STAGES].index("cli") == len(STAGES) - 1


def test_no_two_modules_import_each_other():
    graph = import_graph((HARNESS, ENVS))
    assert "harness.run.ray_executor" not in graph["harness.run.workers"]
    pairs = sorted((a, b) for a in graph for b in graph[a] if a in graph[b] and a < b
                   and not b.startswith(a + ".") and not a.startswith(b + "."))  # a package and its own modules
    assert pairs == []
    assert import_circles(graph) == []


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of `graph` (strongly connected sets of two or more modules, Tarjan's algorithm), an edge
    from a package to its own modules left out (importing `pkg.mod` runs `pkg/__init__` first anyway)."""
    edges = {a: sorted(b for b in graph[a] if not b.startswith(a + ".")) for a in graph}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in edges[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            members = []
            while True:
                member = stack.pop()
                members.append(member)
                if member == node:
                    break
            if len(members) > 1:
                circles.append(sorted(members))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(circles)


def test_the_circle_check_sees_a_circle_and_envs_imports_no_harness():
    """A circle of three (which the pair check misses) is found; envs/ imports nothing of harness/ (the policy side
    never reaches into the simulators, and the simulators know nothing of the policy)."""
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"p": {"p.m"}, "p.m": {"p"}}) == []
    graph = import_graph((HARNESS, ENVS))
    assert "envs.tasks" in graph and "envs.libero_tasks" in graph
    assert sorted(f"{a} imports {b}" for a in graph if a.split(".")[0] == "envs"
                  for b in graph[a] if b.split(".")[0] == "harness") == []


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
