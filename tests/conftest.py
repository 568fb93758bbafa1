import faulthandler
import fcntl
import functools
import os
import tempfile

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

# A test worker that dies in native code (a segfault, an abort) takes its traceback with it:
# pytest-xdist says only "worker crashed". Each worker writes the native and Python stacks to a
# file under CRASH_DIR instead, and the controller lists the tests that crashed and those that
# failed; ./test.sh prints the stacks and runs the crashed tests once more, alone.
CRASH_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".pytest-crash")
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")


@pytest.hookimpl(trylast=True)  # after pytest's own faulthandler plugin, which points it at stderr
def pytest_configure(config):
    if _WORKER:
        os.makedirs(CRASH_DIR, exist_ok=True)
        config._crash_log = open(os.path.join(CRASH_DIR, f"{_WORKER}.log"), "w")  # open while the worker lives
        faulthandler.enable(file=config._crash_log, all_threads=True)
        _render_one_at_a_time()


RENDER_LOCK = os.path.join(tempfile.gettempdir(), "posecal-tests-render.lock")


def _render_one_at_a_time() -> None:
    """Make the test workers' pyrender calls take turns (an exclusive file lock around each renderer's
    creation and each render): software OpenGL aborted in glReadPixels when two workers rendered at once
    (tests/test_sync.py's fixture, once in CI), and pytest-xdist then hung waiting for the dead worker's
    tests. Renders in the service processes that a test starts are not covered."""
    from estimator.render import Renderer

    def locked(method):
        @functools.wraps(method)
        def call(*args, **kwargs):
            with open(RENDER_LOCK, "a") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
                return method(*args, **kwargs)
        return call

    Renderer.__init__ = locked(Renderer.__init__)
    Renderer.render = locked(Renderer.render)
    Renderer.close = locked(Renderer.close)


def pytest_runtest_logreport(report):
    """In the xdist controller: note each failed test, as crashed (its worker died) or failed."""
    if _WORKER or not report.failed or not hasattr(report, "node"):
        return
    os.makedirs(CRASH_DIR, exist_ok=True)
    name = "crashed.txt" if report.when == "???" else "failed.txt"  # xdist's report of a dead worker
    with open(os.path.join(CRASH_DIR, name), "a") as f:
        f.write(report.nodeid + "\n")

MOCAP = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "mocap"))


@pytest.fixture(scope="session")
def mocap_dir() -> str:
    if not os.path.isdir(MOCAP):
        pytest.skip(f"CMU mocap not found at {MOCAP}")
    return MOCAP


@pytest.fixture(scope="session")
def small_model_path() -> str:
    """A small appearance model (15-degree azimuths, 3 elevations, 40 clusters): ~10-30 s to
    build, once for all sessions and test workers (:func:`conftest_service.small_model_path`).

    Tests that need the full 17,280-example model are evaluations, not unit tests.
    """
    from conftest_service import small_model_path as cached

    return str(cached())


@pytest.fixture(scope="session")
def small_model(small_model_path):
    from estimator.appearance import load_model

    return load_model(small_model_path)


TURN_BEFORE, TURN_AFTER = (60.0, 150.0), (150.0, 240.0)


@pytest.fixture(scope="session")
def turn_sequence():
    """Two cameras: 40 frames of a walk, then the walker turns by 90 degrees and walks 40 more.

    The cameras see the walker from ``TURN_BEFORE`` azimuths, then from ``TURN_AFTER``.
    """
    from estimator.synth import SynthSpec, synthesize_turns

    return synthesize_turns([SynthSpec(n_cameras=2, n_frames=40, seed=seed, azimuths=az, elevations=(10.0, 10.0),
                                       image_size=(320, 240)) for seed, az in ((0, TURN_BEFORE), (10, TURN_AFTER))])
