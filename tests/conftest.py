"""Shared test set-up: offline hub, headless GL, and the reference fixture location."""

import os
import sys
import time
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

REPO = Path(__file__).resolve().parents[1]

# One persistent XLA compilation cache for the suite, its worker processes and every subprocess it starts (they
# inherit the environment): a model compiled once is loaded from disk by the next test that builds the same program,
# instead of compiled again (10-30 s each on 2 cores). The cache key holds the program, the jax/jaxlib versions and
# XLA_FLAGS, so a test under another machine's numerics (--xla_cpu_max_isa=SSE4_2) compiles its own, and a loaded
# executable is the compiled one, bit for bit. Kept between sessions under .pytest_cache/ (git-ignored), at most 2 GB.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(REPO / ".pytest_cache" / "jax-compilation"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(2 * 2 ** 30))
# Python's bytecode, likewise. Where the environment forbids writing it (PYTHONDONTWRITEBYTECODE, set on the CI VM),
# each subprocess compiled the ~1,900 modules it imports from source again: about 4 s of CPU a command, measured.
# The bytecode then goes under .pytest_cache/ (PYTHONPYCACHEPREFIX), never beside the sources.
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
    os.environ.setdefault("PYTHONPYCACHEPREFIX", str(REPO / ".pytest_cache" / "pycache"))
    sys.pycache_prefix, sys.dont_write_bytecode = os.environ["PYTHONPYCACHEPREFIX"], False
# Ray reads its token-authentication mode once per process. A test process whose first Ray instance used token
# authentication (Ray's default) cannot then drive a cluster started without it, as the multi-node tests start theirs:
# the cluster's calls to the driver are refused for a missing token, and the cluster cancels the driver's actors
# before they start ("all references to the actor were removed"). Every Ray instance and cluster of the tests runs
# without it, whichever test file ran first in the process.
os.environ["RAY_AUTH_MODE"] = "disabled"
# The reference checkpoints and outputs of the original Octo code live in the repository (tests/fixtures/octo-reference,
# whose README says what made them); OCTO_REFERENCE_FIXTURES points the tests at another copy.
FIXTURES = Path(os.environ.get("OCTO_REFERENCE_FIXTURES", REPO / "tests" / "fixtures" / "octo-reference"))


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    if not (FIXTURES / "README.md").exists():
        raise FileNotFoundError(
            f"reference fixtures not found at {FIXTURES}; restore tests/fixtures/octo-reference from git or set OCTO_REFERENCE_FIXTURES"
        )
    return FIXTURES



# Under pytest-xdist (scripts/test.sh: `-n 2 --dist loadfile --no-loadscope-reorder`) a test file runs on one
# process, so its module-scoped runs are made once, and files are handed out in collection order as each process
# frees up. Longest first (by tests/durations.json, the seconds each file took on a fresh clone, written by
# `scripts/test_timeline.py DIR --write-durations`) keeps both processes busy to the end: the short files fill in
# last. A file the record lacks counts as a median one. It changes only how fast, never what runs.
DURATIONS = Path(__file__).with_name("durations.json")


def pytest_collection_modifyitems(config, items):
    import json
    import statistics

    seconds = json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}
    typical = statistics.median(seconds.values()) if seconds else 0.0

    def expected(item) -> float:
        return seconds.get(Path(str(item.path)).relative_to(REPO).as_posix(), typical)

    items.sort(key=lambda item: -expected(item))  # stable: a file's tests keep their order


# OCTO_TEST_TIMELINE=DIR: each test process appends a line a test to DIR/<process>.jsonl (start, end, node id, and the
# seconds this process spent compiling XLA programs during it), which scripts/test_timeline.py reads to show how the
# two processes were loaded, where one waited on the other, and what compiling costs. Off by default; changes nothing.
_TIMELINE = os.environ.get("OCTO_TEST_TIMELINE")
_timeline_state = {"compile": 0.0}


def _count_compile(event: str, duration: float, **_kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _timeline_state["compile"] += duration


def pytest_runtest_logstart(nodeid, location):
    if _TIMELINE:
        if "listening" not in _timeline_state:
            from jax._src import monitoring

            monitoring.register_event_duration_secs_listener(_count_compile)
            _timeline_state["listening"] = True
        _timeline_state.update(start=time.time(), compile_at_start=_timeline_state["compile"])


def pytest_runtest_logfinish(nodeid, location):
    if _TIMELINE and "start" in _timeline_state:
        import json

        process = os.environ.get("PYTEST_XDIST_WORKER", "main")
        line = {"process": process, "node": nodeid, "start": _timeline_state["start"], "end": time.time(),
                "compile_s": _timeline_state["compile"] - _timeline_state["compile_at_start"]}
        Path(_TIMELINE).mkdir(parents=True, exist_ok=True)
        with open(Path(_TIMELINE) / f"{process}.jsonl", "a") as out:
            out.write(json.dumps(line) + "\n")
