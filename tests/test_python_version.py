"""pyproject.toml's requires-python admits no Python the code cannot import on (issue 71 item 5.13): the code uses
3.11's standard library (enum.StrEnum, tomllib), so the floor is 3.11."""

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# a standard-library name -> the first Python that has it
NEEDS = {"StrEnum": (3, 11), "tomllib": (3, 11)}


def floor(requires: str) -> tuple[int, int]:
    """'>=3.11' -> (3, 11)."""
    return tuple(int(x) for x in re.fullmatch(r">=\s*(\d+)\.(\d+)", requires.strip()).groups())


def test_requires_python_is_at_least_what_the_code_uses():
    requires = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["requires-python"]
    sources = [p.read_text() for package in ("harness", "envs", "reference_policies") for p in (ROOT / package).rglob("*.py")]
    used = {name: version for name, version in NEEDS.items()
            if any(re.search(rf"^\s*(from|import) .*\b{name}\b", text, re.M) for text in sources)}
    assert used == NEEDS  # the premise: both are imported somewhere
    assert floor(requires) >= max(used.values()), f"requires-python {requires!r}, but the code imports {sorted(used)}"


def test_the_floor_is_read_as_written():
    assert floor(">=3.10") == (3, 10) < (3, 11) <= floor(">= 3.11")
