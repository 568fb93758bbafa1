import os

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

MOCAP = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "mocap"))


@pytest.fixture(scope="session")
def mocap_dir() -> str:
    if not os.path.isdir(MOCAP):
        pytest.skip(f"CMU mocap not found at {MOCAP}")
    return MOCAP
