"""`apcg distill` (training/distill.py) and `apcg train --init`: a student fitted to the shipped
default model follows it, the run resumes to the bytes of an uninterrupted one, and what cannot
be distilled or started from is refused by name."""

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import default_model_dir, load_model

torch = pytest.importorskip("torch")

from training.distill import DistillConfig, distill, schedule, step_conditions  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TEACHER = default_model_dir()


def sheet_gap(a, b, codes, pose) -> float:
    """Mean |difference| of two models' hit logits (as the loss sees them) and 10 x offsets."""
    sa, sb = a._run(codes, pose), b._run(codes, pose)
    c = 8.0
    logit = np.abs(c * np.tanh(sa[:, 0] / c) - c * np.tanh(sb[:, 0] / c)).mean()
    near = sb[:, 0] > b.tau - 3.0
    depth = np.abs(sa[:, 1] - sb[:, 1])[near].mean()
    return float(logit + 10.0 * depth)


def test_a_distilled_student_follows_its_teacher(tmp_path):
    cfg = DistillConfig(teacher=str(TEACHER), width=0.25, head="upconv", steps=150,
                        batch_size=64, lr=3e-3, warmup=10, checkpoint_every=1000)
    before = distill(TEACHER, tmp_path / "start", DistillConfig(**{**cfg.__dict__, "steps": 1}),
                     device="cpu", progress=False)
    out = distill(TEACHER, tmp_path / "run", cfg, device="cpu", progress=False)
    assert out["steps"] == 150
    teacher, student = load_model(TEACHER), load_model(out["model"])
    start = load_model(before["model"])
    codes, pose = step_conditions(len(teacher.types.names), 256, seed=99, step=0)
    gap_start, gap_end = sheet_gap(start, teacher, codes, pose), sheet_gap(student, teacher,
                                                                           codes, pose)
    assert gap_end < 0.6 * gap_start, (gap_start, gap_end)
    # the student is a model like any other: the teacher's types, space, lidar and tau
    assert student.family == teacher.family == "apcg-plus"
    assert student.meta["net"]["head"] == "upconv" and student.meta["net"]["width"] == 0.25
    assert student.types.names == teacher.types.names and student.tau == teacher.tau
    assert student.lidar == teacher.lidar
    assert student.meta["distilled"]["teacher"] == str(teacher.directory)
    assert "measured_lidars" not in student.meta  # the teacher's measurements are not its own
    res = student.generate(teacher.condition("A320neo", 5000.0, np.radians(3.5),
                                             np.radians(3.0), 0.0, 0.0))
    assert len(res.table) == 1
    assert (tmp_path / "run" / "model" / "log.csv").read_text().startswith("step,loss_logit")


def _distill_cmd(run: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "apcg_core.cli", "distill", "--teacher", str(TEACHER),
            "-o", str(run), "--width", "0.25", "--steps", "30", "--batch-size", "16",
            "--checkpoint-every", "10", "--device", "cpu", "--no-progress", *extra]


def test_resumed_after_ctrl_c_it_ends_as_an_uninterrupted_run(tmp_path, hold):
    whole = subprocess.run(_distill_cmd(tmp_path / "whole"), capture_output=True, text=True,
                           timeout=300, cwd=ROOT)
    assert whole.returncode == 0, whole.stderr
    run = tmp_path / "cut"
    proc = subprocess.Popen(_distill_cmd(run), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT, env=hold.env("distill.checkpoint-written"))
    hold.wait("distill.checkpoint-written", proc)
    proc.send_signal(signal.SIGINT)
    hold.release("distill.checkpoint-written")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "goes on from the checkpoint at step 10" in err, err[-3000:]
    assert not (run / "model").exists()  # no model from half a run
    again = subprocess.run(_distill_cmd(run, "--resume"), capture_output=True, text=True,
                           timeout=300, cwd=ROOT)
    assert again.returncode == 0, again.stderr
    a = torch.load(tmp_path / "whole" / "checkpoint.pt", weights_only=False)
    b = torch.load(run / "checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == 30
    for k in a["student"]:
        assert torch.equal(a["student"][k], b["student"][k]), k
    for x, y in zip(a["ema"], b["ema"], strict=True):
        assert torch.equal(x, y)
    steps = [int(r.split(",")[0]) for r in (run / "log.csv").read_text().splitlines()[1:]]
    assert steps == [10, 20, 30]  # the rows after the checkpoint were written once


def test_refusals_name_the_value(tmp_path):
    cgan = ROOT / "apcg_core" / "models" / "cgan"
    with pytest.raises(InputError, match="cannot be distilled"):
        distill(cgan, tmp_path / "a", DistillConfig(teacher=str(cgan), steps=1), device="cpu")
    for bad, word in ((dict(width=0.0), "width"), (dict(lr=float("nan")), "lr"),
                      (dict(steps=0), "steps"), (dict(ema=1.0), "ema"),
                      (dict(minutes=-1.0), "minutes")):
        with pytest.raises(InputError, match=word):
            distill(TEACHER, tmp_path / "b", DistillConfig(teacher=str(TEACHER), **bad),
                    device="cpu")
        assert not (tmp_path / "b").exists()  # refused before anything was written
    with pytest.raises(InputError, match="head must be one of conv, upconv"):
        distill(TEACHER, tmp_path / "c", DistillConfig(teacher=str(TEACHER), head="dense",
                                                       steps=1), device="cpu")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep")
    with pytest.raises(InputError, match="not empty"):
        distill(TEACHER, tmp_path / "full", DistillConfig(teacher=str(TEACHER), steps=1),
                device="cpu")
    assert (tmp_path / "full" / "x").read_text() == "keep"
    with pytest.raises(InputError, match="nothing to continue"):
        distill(TEACHER, tmp_path / "none", DistillConfig(teacher=str(TEACHER), steps=1),
                device="cpu", resume=True)


def test_the_schedule_warms_up_then_decays_to_one_percent():
    cfg = DistillConfig(teacher="x", steps=1000, lr=1e-3, warmup=100)
    lrs = [schedule(cfg, s, 0.0) for s in range(1000)]
    assert lrs[0] == pytest.approx(1e-5) and max(lrs) == pytest.approx(1e-3, rel=1e-3)
    assert all(b <= a for a, b in zip(lrs[100:], lrs[101:], strict=False))
    assert schedule(cfg, 1000, 0.0) == pytest.approx(1e-5)
    timed = DistillConfig(teacher="x", steps=10**6, lr=1e-3, warmup=0, minutes=1.0)
    assert schedule(timed, 10, 60.0) == pytest.approx(1e-5)  # time ran out: at the end


def test_train_init_starts_from_the_model_and_refuses_another_network(tiny_training_data,
                                                                      tmp_path):
    from training.export import export_model
    from training.trainer import Trainer, config_from
    cfg = config_from("tiny", family="apcg-plus", steps=300, seed=1, width=0.25, sheet=32,
                      checkpoint_every=10**6, log_every=1)
    Trainer(tiny_training_data, tmp_path / "run", cfg, progress=False).fit()
    model = export_model(tmp_path / "run", tmp_path / "model")

    def first_loss(run, **over):
        c = config_from("tiny", **{**dict(family="apcg-plus", steps=1, seed=2, width=0.25,
                                          sheet=32, checkpoint_every=10**6, log_every=1),
                                   **over})
        Trainer(tiny_training_data, tmp_path / run, c, progress=False).fit()
        row = (tmp_path / run / "log.csv").read_text().splitlines()[1].split(",")
        return float(row[2])  # the first step's cross-entropy

    assert first_loss("warm", init=str(model)) < 0.5 * first_loss("cold")
    with pytest.raises(InputError, match="differs from the run's in width"):
        first_loss("wide", init=str(model), width=0.5)
    with pytest.raises(InputError, match="differs from the run's in head"):
        first_loss("up", init=str(model), head="upconv")
    with pytest.raises(InputError, match="its types are not the dataset's"):
        meta = json.loads((model / "model.json").read_text())
        meta["types"][0]["name"] = "Not In The Dataset"
        other = tmp_path / "reordered"
        other.mkdir()
        (other / "model.json").write_text(json.dumps(meta))
        (other / "sheets.onnx").write_bytes((model / "sheets.onnx").read_bytes())
        first_loss("reordered_run", init=str(other))


def test_the_command_never_writes_into_its_teacher(tmp_path):
    """-o the teacher's own directory: refused by the output guard, even with --force, and
    the teacher's files (its log.csv among them) are as they were."""
    import shutil
    teacher = tmp_path / "teacher"
    shutil.copytree(TEACHER, teacher)
    before = {p.name: p.read_bytes() for p in teacher.iterdir()}
    out = subprocess.run([sys.executable, "-m", "apcg_core.cli", "distill", "--teacher",
                          str(teacher), "-o", str(teacher), "--steps", "2", "--batch-size", "4",
                          "--device", "cpu", "--force", "--no-progress"],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode != 0 and "is an input of this command" in out.stderr, out.stderr
    assert {p.name: p.read_bytes() for p in teacher.iterdir()} == before
