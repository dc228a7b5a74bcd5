"""Training runs are safe to interrupt, resume and restart: Ctrl-C saves a whole step, a resume
refuses settings that differ from the run's, and a run killed before its first checkpoint
starts over in place."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from training.trainer import RESUMABLE, Trainer, config_from

APCG = str(Path(sys.executable).parent / "apcg")


def _train(data, run, *extra, **kw):
    return subprocess.run([APCG, "train", "--data", str(data), "-o", str(run), "--preset",
                           "tiny", "--no-progress", *extra], capture_output=True, text=True,
                          timeout=300, **kw)


def test_ctrl_c_finishes_the_step_saves_and_exits_130(tiny_training_data, tmp_path):
    run = tmp_path / "run"
    proc = subprocess.Popen([APCG, "train", "--data", str(tiny_training_data), "-o", str(run),
                             "--preset", "tiny", "--steps", "100000", "--checkpoint-every",
                             "100000", "--no-progress"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    log = run / "log.csv"
    deadline = time.time() + 120
    while time.time() < deadline and not (log.exists() and len(log.read_text().splitlines())
                                          > 3):
        time.sleep(0.2)
    assert log.exists(), proc.stderr.read() if proc.poll() is not None else "no log"
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "SIGINT" in err and "--resume" in err and "Traceback" not in err
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    rows = log.read_text().splitlines()[1:]
    assert state["step"] >= 3 and int(rows[-1].split(",")[0]) == state["step"]
    more = _train(tiny_training_data, run, "--resume", "--steps", str(state["step"] + 2))
    assert more.returncode == 0, more.stderr
    assert json.loads(more.stdout)["step"] == state["step"] + 2


def test_resume_refuses_settings_that_differ(tiny_training_data, tmp_path):
    run = tmp_path / "run"
    first = _train(tiny_training_data, run, "--steps", "2", "--width", "0.25")
    assert first.returncode == 0, first.stderr
    for extra, needle in ((["--width", "0.5"], "--width 0.5 (the run's: 0.25)"),
                          (["--batch-size", "7"], "--batch-size 7"),
                          (["--seed", "9"], "--seed 9")):
        out = _train(tiny_training_data, run, "--resume", "--steps", "3", *extra)
        assert out.returncode == 2 and needle in out.stderr, out.stderr
    other = tmp_path / "other_data"
    other.symlink_to(tiny_training_data)  # resolves to the same: accepted
    same = _train(other, run, "--resume", "--steps", "3", "--width", "0.25")
    assert same.returncode == 0, same.stderr
    elsewhere = tmp_path / "copy"
    import shutil
    shutil.copytree(tiny_training_data, elsewhere)
    out = _train(elsewhere, run, "--resume", "--steps", "4")
    assert out.returncode == 2 and "--data" in out.stderr and "the run's" in out.stderr
    assert "steps" in RESUMABLE and "width" not in RESUMABLE


def test_resume_compares_a_setting_the_run_predates_with_the_default_it_ran_with(
        tiny_training_data, tmp_path):
    """A run recorded before a setting existed ran with its default: asking another value on
    resume is refused, not silently dropped; asking the default is accepted."""
    run = tmp_path / "run"
    first = _train(tiny_training_data, run, "--family", "apcg-plus", "--sheet", "16",
                   "--steps", "2")
    assert first.returncode == 0, first.stderr
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert state["train"].pop("queries") == "returns"
    torch.save(state, run / "checkpoint.pt")  # as an older version wrote it
    out = _train(tiny_training_data, run, "--resume", "--steps", "3", "--queries", "silhouette")
    assert out.returncode == 2 and "--queries silhouette (the run's: returns)" in out.stderr, \
        out.stderr
    same = _train(tiny_training_data, run, "--resume", "--steps", "3", "--queries", "returns")
    assert same.returncode == 0, same.stderr


def test_a_run_killed_before_its_first_checkpoint_starts_over(tiny_training_data, tmp_path):
    run = tmp_path / "run"
    cfg = config_from("tiny", steps=2, seed=0, checkpoint_every=1000)
    Trainer(tiny_training_data, run, cfg, progress=False).fit()
    (run / "checkpoint.pt").unlink()  # as if killed before any checkpoint was written
    again = _train(tiny_training_data, run, "--resume", "--steps", "2")
    assert again.returncode == 2 and "without --resume" in again.stderr
    fresh = _train(tiny_training_data, run, "--steps", "2")
    assert fresh.returncode == 0 and "starting it over" in fresh.stderr, fresh.stderr
    rows = (run / "log.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == [1, 2]  # the dead run's rows are gone
    with pytest.raises(Exception, match="already holds a training run"):
        Trainer(tiny_training_data, run, cfg, progress=False)


@pytest.mark.parametrize("family_dir,weights", [("default", "sheets.onnx"),
                                                ("cgan", "generator.onnx")])
@pytest.mark.parametrize("runtime", ["onnx", "torch"])
def test_a_corrupt_model_file_is_named(tmp_path, family_dir, weights, runtime):
    import shutil
    src = Path(__file__).resolve().parents[1] / "apcg_core" / "models" / family_dir
    model = tmp_path / "m"
    shutil.copytree(src, model)
    whole = (model / weights).read_bytes()
    (model / weights).write_bytes(whole[:len(whole) // 3])  # a copy cut short
    out = subprocess.run([APCG, "generate", "--model", str(model), "--runtime", runtime,
                          "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
                          "--pitch-deg", "2", "-o", str(tmp_path / "c.ply")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert f"{weights}" in out.stderr and "corrupt" in out.stderr
    assert not (tmp_path / "c.ply").exists()


def test_a_corrupt_checkpoint_is_named(tiny_training_data, tmp_path):
    run = tmp_path / "run"
    assert _train(tiny_training_data, run, "--steps", "1").returncode == 0
    whole = (run / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(whole[:len(whole) // 2])
    for args in (["train", "--data", str(tiny_training_data), "-o", str(run), "--resume"],
                 ["export", "--run", str(run), "-o", str(tmp_path / "m")]):
        out = subprocess.run([APCG, *args], capture_output=True, text=True, timeout=300)
        assert out.returncode == 2 and "not a readable checkpoint" in out.stderr, out.stderr
        assert "Traceback" not in out.stderr
    assert not (tmp_path / "m").exists()


def test_a_second_process_on_a_live_run_is_refused_and_a_dead_ones_lock_is_taken(
        tiny_training_data, tmp_path):
    run = tmp_path / "run"
    first = subprocess.Popen([APCG, "train", "--data", str(tiny_training_data), "-o", str(run),
                              "--preset", "tiny", "--steps", "100000", "--checkpoint-every",
                              "2", "--no-progress"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not (run / "checkpoint.pt").exists():
        time.sleep(0.2)
    assert (run / ".train.lock").read_text().split()[0] == str(first.pid)
    second = _train(tiny_training_data, run, "--resume", "--steps", "100000")
    assert second.returncode == 2, second.stderr
    assert f"pid {first.pid}" in second.stderr and "Traceback" not in second.stderr
    first.kill()  # SIGKILL: the lock stays behind, owned by a dead process
    first.communicate(timeout=60)
    step = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["step"]
    again = _train(tiny_training_data, run, "--resume", "--steps", str(step + 1))
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["step"] == step + 1
    assert not (run / ".train.lock").exists()
