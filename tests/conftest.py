import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("default", deadline=None, max_examples=60,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=150, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

# The tests' user catalog is their own, never the developer's (~/.local/share/apcg): a test that
# adds a type must not leave it there, and a type left there must not change a test. Set
# before anything reads the catalog; the commands the tests start inherit it.
# Each test process (pytest-xdist starts several) makes its own and removes it when it exits:
# a run leaves nothing in the machine's temporary directory.
if "APCG_TEST_KEEP_DATA_DIR" not in os.environ:
    import atexit
    import tempfile
    os.environ["APCG_DATA_DIR"] = tempfile.mkdtemp(prefix="apcg-tests-data-")
    atexit.register(shutil.rmtree, os.environ["APCG_DATA_DIR"], ignore_errors=True)


def pytest_sessionfinish(session, exitstatus):
    # In CI a skipped test is a failed test: CI installs everything the tests need.
    if os.environ.get("APCG_FAIL_ON_SKIP") == "1" and exitstatus == 0:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        skipped = len(reporter.stats.get("skipped", [])) if reporter else 0
        if skipped:
            print(f"\nAPCG_FAIL_ON_SKIP: {skipped} skipped test(s) count as failures")
            session.exitstatus = 1


def pytest_configure(config):
    # A test run started in the background of a script (`pytest ... &`, nohup) inherits Ctrl-C
    # ignored, and so would every command it starts: Python keeps an ignored SIGINT ignored,
    # and the Ctrl-C tests would see their commands run to the end. A handler of our own is
    # reset to the default in each child, so the commands answer Ctrl-C as in a terminal.
    import signal
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # The tests' networks are tiny: one torch thread is as fast, and it keeps a busy machine
    # (another job using every core) from slowing the tests many times over through thread
    # oversubscription.
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_training_data(tmp_path_factory) -> Path:
    """The training tests' dataset (2 types, 192 samples, a 64 x 16 window), built once."""
    from dataset_builder.build import build_dataset
    out = tmp_path_factory.mktemp("tiny_training") / "ds"
    build_dataset(str(Path(__file__).parent / "data" / "dataset_tiny_window.toml"), out,
                  progress=False)
    return out


BLENDER_APT = "apt-get install -y blender python3-numpy (the README's set-up)"


def blender_or_skip() -> str:
    """The ``blender`` binary on PATH, or a skip naming how to install it: the one rule of every
    test that runs the binary (CI's APCG_FAIL_ON_SKIP turns the skip into a failure)."""
    exe = shutil.which("blender")
    if exe is None:
        pytest.skip(f"needs the blender binary, which is not on PATH: {BLENDER_APT}")
    return exe


@pytest.fixture
def blender_binary() -> str:
    return blender_or_skip()


class Hold:
    """Holds a command at named points of ``apcg_core.testpoints`` so that a test interrupts it
    at a known moment, however fast or loaded the machine is."""

    def __init__(self, directory: Path):
        self.directory = directory
        directory.mkdir(parents=True, exist_ok=True)

    def env(self, *points: str) -> dict:
        """This process's environment, plus what makes a command wait at ``points``."""
        from apcg_core.testpoints import ENV_AT, ENV_DIR, POINTS
        unknown = [p for p in points if p not in POINTS]
        assert not unknown, f"unknown test points {unknown}; known: {list(POINTS)}"
        return {**os.environ, ENV_AT: ",".join(points), ENV_DIR: str(self.directory)}

    def wait(self, point: str, proc: subprocess.Popen, timeout: float = 300) -> int:
        """Until some process of ``proc`` waits at ``point``; returns that process's pid.
        Fails, with the command's stderr, if ``proc`` ends first."""
        reached = self.directory / f"{point}.reached"
        deadline = time.monotonic() + timeout
        while not reached.exists():
            if proc.poll() is not None:
                err = proc.stderr.read() if proc.stderr else ""
                pytest.fail(f"the command ended (exit {proc.returncode}) before reaching "
                            f"{point}: {err[-2000:] if err else ''}")
            assert time.monotonic() < deadline, f"{point} not reached in {timeout} s"
            time.sleep(0.005)
        return int(reached.read_text())

    def release(self, point: str) -> None:
        """Let every process waiting at ``point`` (and all that come later) go on."""
        (self.directory / f"{point}.go").touch()


@pytest.fixture
def hold(tmp_path_factory) -> Hold:
    return Hold(tmp_path_factory.mktemp("test-points"))  # not in tmp_path: tests list that


@pytest.fixture
def lidar_and_jet(addon_scene, request):
    """``addon_scene`` with a lidar and an A320neo target at the test module's pose ``GOOD``."""
    from blender_addon import api
    lidar = api.add_lidar()
    return lidar, api.add_aircraft(lidar, "A320neo", **request.module.GOOD)


@pytest.fixture
def addon_scene(tmp_path, monkeypatch):
    """An empty Blender scene (the bpy module) with the add-on registered, and a user catalog
    of its own (APCG_DATA_DIR)."""
    bpy = pytest.importorskip("bpy")
    import blender_addon
    from apcg_core.catalog import default_catalog
    monkeypatch.setenv("APCG_DATA_DIR", str(tmp_path / "data"))
    default_catalog.cache_clear()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    yield bpy.context.scene
    blender_addon.unregister()
    default_catalog.cache_clear()


@pytest.fixture
def own_catalog(tmp_path, monkeypatch):
    """A user catalog of the test's own (APCG_DATA_DIR): the user types it adds do not stay in
    this process's catalog for the tests after it (a shipped model's types are counted
    against the catalog's)."""
    from apcg_core.catalog import default_catalog
    monkeypatch.setenv("APCG_DATA_DIR", str(tmp_path / "own-data"))
    default_catalog.cache_clear()
    yield
    default_catalog.cache_clear()
