"""Layout: an explicit stage order that no import runs back up, no two harness modules import each other (one place
chooses the executor), no compatibility layer; the reference policies' package beside the harness, never inside it."""

import ast
from pathlib import Path

HARNESS = Path(__file__).resolve().parents[1] / "harness"
ENVS = HARNESS.parent / "envs"
REFERENCE = HARNESS.parent / "reference_policies"  # an application of the harness: its own package and extra

# The data path, lowest stage first. A module may import its own stage and the stages before it, never a later one.
# `measures` (the per-step maths: attention slicing, attribution, deletion fills, the controls' frame transforms;
# and the success statistics the run store writes) and `probes` (the per-step probes, PROBE_PARTS below) sit below
# `policy`, which computes them at a step; `runfolder` (a run folder's schema, integrity and platform record) sits
# below both `run` (which writes run folders) and `analysis` (which reads them, offline, above the run store). The
# gate commands (regress, replay, sanity, view, robustness grids) read analysis and run the run store, so they sit
# above both; nothing but the command line sits above `report`. The reference policies (reference_policies/) are no
# stage: they sit beside the harness and use its public API (test_the_reference_policies_sit_beside_the_harness).
STAGES = (
    ("envs", ("envs",)),
    ("base", ("harness", "harness.files", "harness.console")),
    ("octo", ("harness.octo",)),
    ("measures", ("harness.measures",)),
    ("probes", ("harness.probes",)),
    ("policy", ("harness.interventions", "harness.policy", "harness.policy_config", "harness.conventions", "harness.policies")),
    ("rollout", ("harness.records", "harness.rollout")),
    ("outputs", ("harness.outputs",)),
    ("runfolder", ("harness.runfolder",)),
    ("run", ("harness.run",)),
    ("analysis", ("harness.analysis",)),
    ("gate", ("harness.gate",)),
    ("report", ("harness.report",)),
    ("cli", ("harness.cli",)),
)


# A per-step probe is one folder, harness/probes/<probe>/: the probe itself at the `probes` stage (between the maths it
# computes with and the policy that calls it), and the parts its registry entry names, each at the stage that uses
# it: the sink and the viewer layer with the writers, the reader with the analysis, the report section with the report.
PROBE_PARTS = {"sink": "outputs", "viewer": "outputs", "reader": "analysis", "report": "report"}


def stage_of(module: str) -> int:
    """Index in STAGES of the longest prefix naming `module` (a package holds its modules); a probe's part
    (harness.probes.<probe>.<part>, PROBE_PARTS) is at its part's stage."""
    parts = module.split(".")
    if len(parts) >= 4 and parts[:2] == ["harness", "probes"] and parts[3] in PROBE_PARTS:
        return [name for name, _ in STAGES].index(PROBE_PARTS[parts[3]])
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
    assert stage_of("harness.measures.attribution") < stage_of("harness.probes.reliance") < stage_of("harness.policy")
    assert stage_of("harness.probes.reliance.sink") == stage_of("harness.outputs.sinks")
    assert stage_of("harness.probes.reliance.report") == stage_of("harness.report.build")
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
    """The import circles of `graph` (strongly connected sets of two or more modules, Tarjan's algorithm). An edge
    from a package to its own modules counts: a package whose `__init__` imports a submodule that imports the package
    back works only while the import that closes the circle comes last (the probe registry did, issue 72)."""
    edges = {a: sorted(graph[a]) for a in graph}
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
    assert import_circles({"p": {"p.m"}, "p.m": {"p"}}) == [["p", "p.m"]]  # a package and its own module
    assert import_circles({"p": {"p.r"}, "p.r": set(), "p.b": {"p.r"}}) == []  # the registry's shape: one direction
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


def imports_of(source: str) -> list[tuple[str, str | None]]:
    """(module, name) of every import in `source`, top level or inside functions: `import a.b` is ("a.b", None),
    `from a.b import c` is ("a.b", "c")."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            found += [(node.module, a.name) for a in node.names]
    return found


def private_imports(source: str, packages=("harness", "envs", "reference_policies")) -> list[str]:
    """The imports in `source` that reach a private name (a module or a name starting with `_`) of `packages`."""
    return sorted(f"{module}{'.' + name if name else ''}" for module, name in imports_of(source)
                  if module.split(".")[0] in packages
                  and any(part.startswith("_") for part in module.split(".") + [name or ""]))


def test_the_reference_policies_sit_beside_the_harness():
    """No module of harness/ or envs/ imports the reference policies or optax (the training's own dependency, in the
    `train` extra); the reference policies use only public names of the harness (and of each other's modules); their
    own modules form no circle. The private-name check can fail: a hand-made `from harness.x import _y` is caught."""
    core = [p for root in (HARNESS, ENVS) for p in root.rglob("*.py")]
    assert len(core) > 60
    reaching = sorted(f"{p.relative_to(HARNESS.parent)} imports {module}" for p in core
                      for module, _ in imports_of(p.read_text())
                      if module.split(".")[0] in ("reference_policies", "optax"))
    assert reaching == []
    modules = sorted(REFERENCE.rglob("*.py"))
    assert len(modules) > 10 and not (HARNESS / "reference").exists()
    assert sorted(f"{p.name}: {name}" for p in modules for name in private_imports(p.read_text())) == []
    assert private_imports("from harness.octo import _x\nimport harness._y\nfrom numpy import _z") == \
        ["harness._y", "harness.octo._x"]
    graph = import_graph((REFERENCE,))
    assert "reference_policies.train" in graph["reference_policies.pipeline"]
    assert import_circles(graph) == []


def test_every_module_imports_and_states_its_job():
    """The quick subset (`pytest -m "not slow"`) imports every module of harness/, envs/ and reference_policies/
    here, so none is left out of it; each module's docstring states its job."""
    import importlib

    root = HARNESS.parent
    names = sorted(".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
                   for package in ("harness", "envs", "reference_policies")
                   for p in (root / package).rglob("*.py"))
    undocumented = [name for name in names if not (importlib.import_module(name).__doc__ or "").strip()]
    assert len(names) > 60 and undocumented == []


def test_only_the_factory_constructs_a_policy():
    """Issue 73: outside the Octo implementation (harness/octo/, harness/policies/octo.py) and the factory
    (harness/policies/registry.py), nothing in harness/, envs/, reference_policies/, benchmarks/, scripts/ or examples/
    loads an Octo model or builds its inference: they call harness.policies.load_policy / Policy.inference."""
    allowed = {"harness/policies/octo.py", "harness/policies/registry.py"}
    calls = {"load_pretrained", "OctoCheckpoint", "BatchInference", "OctoModel"}
    found = []
    root = HARNESS.parent
    for folder in ("harness", "envs", "reference_policies", "benchmarks", "scripts", "examples"):
        for path in (root / folder).rglob("*.py"):
            name = path.relative_to(root).as_posix()
            if name.startswith("harness/octo/") or name in allowed:
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                func = node.func if isinstance(node, ast.Call) else None
                called = getattr(func, "id", None) or getattr(func, "attr", None)
                if called in calls:
                    found.append(f"{name}:{node.lineno} {called}(...)")
    assert found == []


def test_the_command_line_imports_nothing_heavy_before_its_ctrl_c_handler():
    """`from harness.cli import main` (what runs before main() installs the SIGINT handler) imports no numpy, JAX,
    simulator or policy: a Ctrl-C in those imports would be a traceback and exit -2, not 130 (the serve command's
    module once imported the policy server at its top; tests/runfolder/test_hostile_inputs.py caught it under load)."""
    import subprocess
    import sys

    heavy = ("numpy", "jax", "mujoco", "robosuite", "websockets", "harness.policies", "harness.policy", "harness.run")
    code = f"import sys; from harness.cli import main; print([m for m in {heavy!r} if m in sys.modules])"
    done = subprocess.run([sys.executable, "-c", code], cwd=HARNESS.parent, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stdout + done.stderr
