import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("default", deadline=None, max_examples=60,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=150, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


def pytest_sessionfinish(session, exitstatus):
    # In CI a skipped test is a failed test: CI installs everything the tests need.
    if os.environ.get("APCG_FAIL_ON_SKIP") == "1" and exitstatus == 0:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        skipped = len(reporter.stats.get("skipped", [])) if reporter else 0
        if skipped:
            print(f"\nAPCG_FAIL_ON_SKIP: {skipped} skipped test(s) count as failures")
            session.exitstatus = 1


def pytest_configure(config):
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
