"""Shared test set-up: offline hub, headless GL, and the reference fixture location."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(os.environ.get("OCTO_REFERENCE_FIXTURES", REPO.parent / "shared" / "fixtures" / "octo-reference"))


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    if not (FIXTURES / "README.md").exists():
        raise FileNotFoundError(
            f"reference fixtures not found at {FIXTURES}; place ../shared next to the repo or set OCTO_REFERENCE_FIXTURES"
        )
    return FIXTURES
