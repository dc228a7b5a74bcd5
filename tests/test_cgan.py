"""The cGAN: structure of SPEC section 7, the gradient penalty, training, resume, data
parallelism, export to ONNX and generation."""

import csv
import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from apcg_core.errors import InputError
from apcg_core.families.cgan import APCGModel
from apcg_core.nn.cgan import Discriminator, Generator, NetConfig, SelfAttention
from training.data import DepthDataset
from training.export import export_model
from training.trainer import Trainer, TrainingDiverged, config_from, gradient_penalty


@pytest.fixture
def data(tiny_training_data) -> Path:
    return tiny_training_data


def test_generator_structure_is_the_papers():
    g = Generator(NetConfig())
    convs = [m for m in g.modules() if isinstance(m, nn.ConvTranspose2d)]
    assert len(convs) == 5
    shapes = []
    hooks = [m.register_forward_hook(lambda m, i, o: shapes.append(tuple(o.shape[1:])))
             for m in convs]
    g.eval()
    with torch.no_grad():
        out = g(torch.zeros(1, 100), torch.zeros(1, 6))
    for h in hooks:
        h.remove()
    assert shapes == [(512, 4, 16), (256, 8, 32), (128, 16, 64), (64, 32, 128), (1, 64, 256)]
    assert convs[0].in_channels == 106
    assert sum(isinstance(m, SelfAttention) for m in g.modules()) == 1
    assert g.attention.value.in_channels == 512  # attached to the first layer
    bns = [m for m in g.modules() if isinstance(m, nn.BatchNorm2d)]
    assert [b.num_features for b in bns] == [256, 128, 64]
    assert isinstance(g.out[-1], nn.Tanh) and out.abs().max() <= 1


def test_discriminator_structure_is_the_papers():
    d = Discriminator(NetConfig())
    convs = [m for m in d.features if isinstance(m, nn.Conv2d)]
    assert len(convs) == 4 and convs[0].in_channels == 7
    assert [c.out_channels for c in convs] == [64, 128, 256, 512]
    layers = list(d.features)
    sa = [i for i, m in enumerate(layers) if isinstance(m, SelfAttention)]
    assert len(sa) == 1 and sa[0] > layers.index(convs[3])
    assert not any(isinstance(m, (nn.BatchNorm2d, nn.BatchNorm1d)) for m in d.modules())
    linears = [m for m in d.modules() if isinstance(m, nn.Linear)]
    assert len(linears) == 1 and linears[0].out_features == 1
    assert d(torch.zeros(3, 1, 64, 256), torch.zeros(3, 6)).shape == (3,)


@pytest.mark.parametrize("conv", [True, False])
@pytest.mark.parametrize("attention", [True, False])
def test_ablation_variants_build_and_run(conv, attention):
    cfg = NetConfig(width=0.125, conv=conv, attention=attention)
    g, d = Generator(cfg), Discriminator(cfg)
    x = g(torch.randn(2, 100), torch.zeros(2, 6))
    assert x.shape == (2, 1, 64, 256)
    assert d(x, torch.zeros(2, 6)).shape == (2,)
    assert any(isinstance(m, nn.ConvTranspose2d) for m in g.modules()) == conv
    assert any(isinstance(m, SelfAttention) for m in g.modules()) == attention


class _Linear(nn.Module):
    def __init__(self, w):
        super().__init__()
        self.w = nn.Parameter(w)

    def forward(self, x, nu):
        return (x * self.w).flatten(1).sum(1)


def test_gradient_penalty_hand_computed_and_finite_at_zero_gradient():
    torch.manual_seed(0)
    w = torch.zeros(1, 1, 2, 2)
    w[0, 0, 0, 0], w[0, 0, 1, 1] = 3.0, 4.0  # ||grad|| = 5 everywhere
    d = _Linear(w)
    real, fake = torch.randn(4, 1, 2, 2), torch.randn(4, 1, 2, 2)
    gp = gradient_penalty(d, real, fake, torch.zeros(4, 6), torch.rand(4))
    assert float(gp.detach()) == pytest.approx((5.0 - 1.0) ** 2, rel=1e-6)
    gp.backward()
    # d/dw of (||w|| - 1)^2 = 2 (||w|| - 1) w / ||w||
    assert torch.allclose(d.w.grad, 2 * 4 * w / 5, atol=1e-5)
    zero = _Linear(torch.zeros(1, 1, 2, 2))
    gp0 = gradient_penalty(zero, real, fake, torch.zeros(4, 6), torch.rand(4))
    assert float(gp0.detach()) == pytest.approx(1.0, abs=1e-5)
    gp0.backward()
    assert torch.isfinite(zero.w.grad).all()


def _losses(run: Path):
    with open(run / "log.csv") as f:
        return [(r["step"], r["loss_d"], r["loss_g"], r["gp"]) for r in csv.DictReader(f)]


def test_resume_continues_exactly(data, tmp_path):
    cfg = config_from("tiny", steps=6, checkpoint_every=3, seed=4)
    full = Trainer(data, tmp_path / "full", cfg, progress=False)
    full.fit()
    part = Trainer(data, tmp_path / "part", cfg, progress=False)
    part.fit(max_seconds=0.0)  # one step, then it stops and checkpoints
    while part.step < 3:
        part.train_step()
    part.save()
    # the log may hold rows past the checkpoint in a real crash; they are dropped on resume
    again = Trainer(data, tmp_path / "part", cfg, resume=True, progress=False)
    assert again.step == 3
    again.fit()
    assert _losses(tmp_path / "full")[3:] == _losses(tmp_path / "part")[-3:]
    with open(tmp_path / "part" / "log.csv") as f:
        clock = [float(r["seconds"]) for r in csv.DictReader(f)]
    assert clock == sorted(clock) and clock[0] > 0  # training time accumulates across runs
    for a, b in zip(full.G.state_dict().values(), again.G.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(Exception, match="already holds a training run"):
        Trainer(data, tmp_path / "full", cfg, progress=False)


def test_generator_average_is_exact_resumable_and_exported(data, tmp_path):
    from training.trainer import ema_update
    a, b = torch.nn.BatchNorm1d(2), torch.nn.BatchNorm1d(2)
    with torch.no_grad():
        a.weight.copy_(torch.tensor([1.0, 2.0]))
        b.weight.copy_(torch.tensor([3.0, 6.0]))
        b.running_mean.copy_(torch.tensor([0.5, -0.5]))
    ema_update(a, b, 0.75)  # 0.75 * [1, 2] + 0.25 * [3, 6]
    assert torch.allclose(a.weight, torch.tensor([1.5, 3.0]))
    assert torch.equal(a.running_mean, b.running_mean)  # statistics follow the live network
    cfg = config_from("tiny", steps=6, checkpoint_every=3, seed=5, ema=0.9)
    full = Trainer(data, tmp_path / "full", cfg, progress=False)
    full.fit()
    diff = [float((p - q).detach().abs().max()) for p, q in zip(full.G.parameters(),
                                                       full.G_ema.parameters(), strict=True)]
    assert max(diff) > 0  # the average lags the weights
    part = Trainer(data, tmp_path / "part", replace(cfg, steps=3), progress=False)
    part.fit()
    again = Trainer(data, tmp_path / "part", cfg, resume=True, progress=False)
    again.fit()
    for x, y in zip(full.G_ema.state_dict().values(), again.G_ema.state_dict().values(),
                    strict=True):
        assert torch.equal(x, y)  # the average is checkpointed: resume stays exact
    # switched on when resuming a run that had none: it starts from the weights of that step
    plain = Trainer(data, tmp_path / "plain", replace(cfg, ema=0.0, steps=3), progress=False)
    plain.fit()
    late = Trainer(data, tmp_path / "plain", cfg, resume=True, progress=False)
    assert late.ema_since == 3 and all(torch.equal(x, y) for x, y in zip(
        late.G.parameters(), late.G_ema.parameters(), strict=True))
    late.fit()
    out = export_model(tmp_path / "full", tmp_path / "m")
    meta = json.loads((out / "model.json").read_text())
    assert meta["generator_weights"].startswith("moving average (decay 0.9)")
    model = APCGModel(out, runtime="torch")
    for k, v in full.G_ema.state_dict().items():
        if v.is_floating_point():  # (BatchNorm's batch counter is not part of the model)
            assert torch.equal(model.torch_generator().state_dict()[k], v), k
    raw = APCGModel(export_model(tmp_path / "full", tmp_path / "raw", raw=True), runtime="torch")
    assert raw.meta["generator_weights"] == "raw"
    k = next(iter(full.G.state_dict()))
    assert torch.equal(raw.torch_generator().state_dict()[k], full.G.state_dict()[k])

def _image_distance(model_g, ds: DepthDataset, n=64, seed=0):
    """Mean absolute difference between the mean generated and mean real training image, and
    between the generated and real target occupancy rates."""
    idx = np.random.default_rng(seed).choice(len(ds), n, replace=False)
    real = ds.images(idx)
    model_g.eval()
    with torch.no_grad():
        fake = model_g(torch.randn(n, 100, generator=torch.Generator().manual_seed(seed)),
                       torch.from_numpy(ds.nu[idx]))[:, 0].numpy()
    return float(np.abs(real.mean(0) - fake.mean(0)).mean())


def test_training_reduces_the_distance_to_the_data(data, tmp_path):
    cfg = config_from("tiny", steps=300, width=0.125, checkpoint_every=1000, seed=1,
                      log_every=50)
    tr = Trainer(data, tmp_path / "run", cfg, progress=False)
    ds = DepthDataset(data, "train")
    before = _image_distance(tr.G, ds)
    tr.fit()
    after = _image_distance(tr.G, ds)
    assert after < 0.5 * before, (before, after)


def _in_own_temp(tmp_path) -> dict:
    """The environment of a torchrun under test: its temporary files (torchelastic's log
    folder, which it never removes) in the test's own folder, not the machine's."""
    (tmp_path / "tmp").mkdir(exist_ok=True)
    return {**os.environ, "TMPDIR": str(tmp_path / "tmp")}


def test_two_process_data_parallel_training_stays_in_sync(data, tmp_path):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "apcg_core.cli", "train", "--data", str(data),
           "-o", str(tmp_path / "ddp"), "--preset", "tiny", "--steps", "3", "--no-progress",
           "--threads", "1"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                         env=_in_own_temp(tmp_path))
    assert run.returncode == 0, run.stderr[-3000:]
    rows = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert sorted(r["rank"] for r in rows) == [0, 1]
    assert rows[0]["step"] == rows[1]["step"] == 3
    assert rows[0]["param_checksum"] == rows[1]["param_checksum"]
    assert (tmp_path / "ddp" / "checkpoint.pt").exists()


def test_an_hours_budget_stops_training_and_holds_across_resumes(data, tmp_path):
    cfg = config_from("tiny", steps=100000, checkpoint_every=1000, seed=3, hours=0.0004)
    first = Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    seconds = [float(r["seconds"]) for r in csv.DictReader(open(tmp_path / "run" / "log.csv"))]
    assert 0 < first["step"] < 100000 and seconds[-1] >= 1.44 > seconds[-2]
    again = Trainer(data, tmp_path / "run", cfg, resume=True, progress=False).fit()
    assert again["step"] == first["step"]  # the budget is spent: a resume adds nothing
    more = Trainer(data, tmp_path / "run", replace(cfg, hours=0.0008), resume=True,
                   progress=False).fit()
    assert more["step"] > first["step"]
    record = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert record["train"]["hours"] == 0.0008  # the record follows the resume's budget
    seconds = [float(r["seconds"]) for r in csv.DictReader(open(tmp_path / "run" / "log.csv"))]
    assert seconds[-1] >= 2.88 > seconds[-2] and np.all(np.diff(seconds) > 0)
    with pytest.raises(Exception, match=r"hours .* must be > 0, got -1"):
        Trainer(data, tmp_path / "bad", replace(cfg, hours=-1.0), progress=False)


def test_export_counts_epochs_over_every_process_batches(data, tmp_path):
    """With torchrun's world W every count of the batch counter is W batches (one per rank):
    the exported epoch count divides by the batches per epoch of W processes."""
    cfg = config_from("tiny", steps=3, seed=4, checkpoint_every=1000)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()  # batch counter 3 (n_critic 1)
    ds = DepthDataset(data, "train")
    record_path = tmp_path / "run" / "train_config.json"
    record = json.loads(record_path.read_text())
    assert record["world"] == 1
    one = json.loads((export_model(tmp_path / "run", tmp_path / "m1") / "model.json")
                     .read_text())
    assert one["trained_epochs"] == round(3 / ds.batches_per_epoch(32, 1), 3)
    record_path.write_text(json.dumps({**record, "world": 2}))  # as a 2-process run records it
    two = json.loads((export_model(tmp_path / "run", tmp_path / "m2") / "model.json")
                     .read_text())
    assert ds.batches_per_epoch(32, 2) != ds.batches_per_epoch(32, 1)
    assert two["trained_epochs"] == round(3 / ds.batches_per_epoch(32, 2), 3)


def test_export_never_overwrites_and_never_leaves_half_a_model(data, tmp_path):
    cfg = config_from("tiny", steps=1, seed=0, checkpoint_every=1000)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's own")
    with pytest.raises(InputError, match="already holds files.*--force"):
        export_model(tmp_path / "run", mine)
    assert (mine / "notes.txt").read_text() == "the user's own"
    with pytest.raises(InputError, match="is the run directory itself"):
        export_model(tmp_path / "run", tmp_path / "run")
    out = export_model(tmp_path / "run", mine, force=True)  # the model's files written in
    assert out == mine and (mine / "model.json").exists()
    assert (mine / "notes.txt").read_text() == "the user's own"  # --force deletes nothing else
    # a failing export leaves neither the final name nor its staging directory behind
    with pytest.raises(InputError):
        export_model(tmp_path / "run", tmp_path / "half", checkpoint=tmp_path / "none.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "run"]


def test_a_run_saved_with_removed_settings_still_resumes(data, tmp_path):
    """Configurations saved before `extra` and `channels_last` went still load and resume."""
    from training.trainer import TrainConfig
    cfg = config_from("tiny", steps=2, seed=4, checkpoint_every=1)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    ck = tmp_path / "run" / "checkpoint.pt"
    st = torch.load(ck, map_location="cpu", weights_only=False)
    st["train"] = {**st["train"], "channels_last": False, "extra": {}}
    torch.save(st, ck)
    assert TrainConfig.from_dict(st["train"]) == cfg
    with pytest.raises(InputError, match=r"unknown settings \['gizmo'\]"):
        TrainConfig.from_dict({**st["train"], "gizmo": 1})
    from apcg_core.cli import main
    assert main(["train", "--data", str(data), "-o", str(tmp_path / "run"), "--resume",
                 "--steps", "3", "--no-progress"]) == 0
    assert torch.load(ck, map_location="cpu", weights_only=False)["step"] == 3


def test_a_budget_is_spent_by_a_step_logged_exactly_on_it():
    from training.trainer import budget_seconds
    assert 0.0004 * 3600.0 > 1.44  # floating point: the raw product is never reached by 1.440
    assert budget_seconds(0.0004) <= 1.44 and budget_seconds(0.0008) <= 2.88
    assert budget_seconds(1.0) == 3600.0


def test_two_processes_stop_together_on_an_hours_budget(data, tmp_path):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "apcg_core.cli", "train", "--data", str(data), "-o", str(tmp_path / "ddp"),
           "--preset", "tiny", "--steps", "100000", "--hours", "0.001", "--no-progress",
           "--threads", "1"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                         env=_in_own_temp(tmp_path))
    assert run.returncode == 0, run.stderr[-3000:]
    rows = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert sorted(r["rank"] for r in rows) == [0, 1]
    assert 0 < rows[0]["step"] == rows[1]["step"] < 100000
    assert rows[0]["param_checksum"] == rows[1]["param_checksum"]


def test_onnx_matches_torch_and_generation_is_seeded(data, tmp_path):
    cfg = config_from("tiny", steps=5, seed=2)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model_dir = export_model(tmp_path / "run", tmp_path / "model")
    onnx_m = APCGModel(model_dir, runtime="onnx")
    torch_m = APCGModel(model_dir, runtime="torch")
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((16, 100))
    nu = rng.uniform(-1, 1, (16, 6))
    a, b = onnx_m.images_from(noise, nu), torch_m.images_from(noise, nu)
    assert np.abs(a - b).max() < 1e-4
    table = torch_m.condition("A320neo", 4500.0, 0.06, 0.04, 0.2, 0.0)
    r1 = torch_m.generate(table, count=3, seed=7)
    r2 = onnx_m.generate(table, count=3, seed=7)
    r3 = torch_m.generate(table, count=3, seed=8)
    assert r1.images.shape == (3, 16, 64)
    assert np.array_equal(r1.cloud.cell_w, r2.cloud.cell_w)
    assert not np.array_equal(r1.images, r3.images)
    with pytest.raises(InputError, match="'A380-800' is not one model .* knows"):
        torch_m.types.code("A380-800")


def test_snapshots_and_divergence_guard(data, tmp_path):
    cfg = config_from("tiny", steps=60, checkpoint_every=10, keep_every=20, seed=2,
                      diverge_gp=0.0)
    Trainer(data, tmp_path / "ok", cfg, progress=False).fit()
    assert [p.name for p in sorted((tmp_path / "ok" / "checkpoints").glob("*.pt"))] == [
        "step-000020.pt", "step-000040.pt", "step-000060.pt"]
    # a threshold no healthy run stays under: the guard stops at step 50, keeps step 40's state
    tr = Trainer(data, tmp_path / "bad", replace(cfg, diverge_gp=1e-9), progress=False)
    with pytest.raises(TrainingDiverged, match=r"diverged at step 50: mean gradient penalty.*"
                                               r"step-000040\.pt"):
        tr.fit()
    saved = torch.load(tmp_path / "bad" / "checkpoint.pt", map_location="cpu",
                       weights_only=False)
    assert saved["step"] == 40


def test_figures_13_and_14_from_a_run(data, tmp_path):
    from training.figures import fig13, fig14, read_log
    bpe = DepthDataset(data, "train").batches_per_epoch(32)
    cfg = config_from("tiny", steps=2 * bpe + 2, width=0.0625, checkpoint_every=bpe,
                      keep_every=bpe, seed=6)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    d13 = fig13(tmp_path / "run", tmp_path / "f13.png")
    assert d13["command"] == f"apcg figure 13 --run {tmp_path / 'run'} -o {tmp_path / 'f13.png'}"
    assert d13["epoch"] == [1, 2, 3] and all(v >= 0 for v in d13["abs_loss_d"])
    log = read_log(tmp_path / "run")
    assert np.all(np.diff(log["hours"]) >= 0)
    d14 = fig14(tmp_path / "run", data, tmp_path / "f14.png", n_pairs=20)
    rows = d14["runs"]["run"]
    assert [r["step"] for r in rows] == [bpe, 2 * bpe]
    assert rows[0]["hours"] <= rows[1]["hours"]
    both = fig14({"a": tmp_path / "run", "b": tmp_path / "run"}, data, tmp_path / "g14.png",
                 n_pairs=20, tau=-0.5)  # several runs scored on the same pairs, at one tau
    assert both["runs"]["a"] == both["runs"]["b"] and both["tau"] == -0.5
    assert "--run a=" in both["command"] and "--tau -0.5" in both["command"]
    last = fig14(tmp_path / "run", data, tmp_path / "h14.png", n_pairs=20, max_checkpoints=1)
    assert last["runs"]["run"] == rows[1:]  # at most one: the last kept checkpoint
    assert "--max-checkpoints 1" in last["command"]
    for name in ("f13.png", "f13.json", "f14.png", "f14.json"):
        assert (tmp_path / name).stat().st_size > 0


def test_evenly_spaced_checkpoints_keep_the_last():
    from training.figures import spaced
    assert spaced(27, 10) == [0, 3, 6, 9, 12, 14, 17, 20, 23, 26]
    assert spaced(27, 1) == [26] and spaced(3, 2) == [0, 2] and spaced(4, None) == [0, 1, 2, 3]
    assert spaced(2, 5) == [0, 1]
    with pytest.raises(InputError, match="max_checkpoints must be >= 1, got 0"):
        spaced(5, 0)


def test_a_model_trained_without_norm_generates_without_denorm(data, tmp_path):
    cfg = config_from("tiny", steps=2, width=0.0625, checkpoint_every=1000, seed=7, norm=False)
    tr = Trainer(data, tmp_path / "run", cfg, progress=False)
    idx = tr.data.batch_indices(cfg.seed, 0, cfg.batch_size)
    raw = tr.data.images(idx, normalized=False)
    real, _ = tr.next_batch()
    assert np.array_equal(real[:, 0].numpy(), raw)  # the images it learns are not normalised
    tr.fit()
    model = APCGModel(export_model(tmp_path / "run", tmp_path / "m"), runtime="onnx")
    assert model.meta["norm"] is False and model.norm is False
    res = model.generate(DepthDataset(data, "test").condition_rows(np.arange(4)), seed=2)
    img = model.images_from(np.random.default_rng(2).standard_normal((4, 100)),
                            model.space.encode(res.table))
    assert np.allclose(res.images, img)  # no DeNorm between the generator and Im2PC


def test_jsd_bins_study_separates_good_from_wrong(data, tmp_path):
    from training.evaluate import jsd_bins_study
    cfg = config_from("tiny", steps=2, width=0.0625, checkpoint_every=1000, seed=8)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = APCGModel(export_model(tmp_path / "run", tmp_path / "m"), runtime="onnx")
    study = jsd_bins_study(model, data, bins=(2, 4, 28), per_band=6)
    assert study["half"] == "validation"  # the choice is made where scores are not reported
    bands = study["bins"].values()
    for c in ("2", "4", "28"):  # a copy 5 m off scores worse than the jittered copy, on average
        assert np.mean([b[c]["wrong"] for b in bands]) > np.mean([b[c]["floor"] for b in bands])
    for band in bands:  # more bins: the floor rises toward 1 (sparse clouds, SPEC section 9)
        assert band["28"]["floor"] >= band["2"]["floor"]
    assert study["best"] in (2, 4, 28)
    assert study["min_gap"][str(study["best"])] == max(study["min_gap"].values())


def test_figures_18_and_19(data, tmp_path):
    from training.figures import fig18, fig19
    cfg = config_from("tiny", steps=2, width=0.0625, checkpoint_every=1000, seed=9)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = APCGModel(export_model(tmp_path / "run", tmp_path / "m"), runtime="onnx")
    d18 = fig18(model, tmp_path / "f18.png", counts=(4, 16))
    kinds = [t for t in (2, 4, 8) if t <= len(model.types)]  # the tiny dataset has few types
    assert [(r["types"], r["clouds"]) for r in d18["rows"]] == [
        (t, n) for t in kinds for n in (4, 16)]
    assert all(r["seconds"] > 0 for r in d18["rows"])
    d19 = fig19(model, data, tmp_path / "f19.png", n_pairs=30, n_bins=2)
    rows = d19.get("aircraft", []) + d19.get("drone", [])
    assert sum(r["pairs"] for r in rows) == d19["pairs"] and 20 <= d19["pairs"] <= 30
    for r in rows:  # both references scored, per range bin
        assert r["mmd_standard"] is None or r["mmd_standard"] >= 0
        assert ("mmd_noised" in r) and ("jsd_noised" in r)
    assert (tmp_path / "f18.json").exists() and (tmp_path / "f19.png").stat().st_size > 0
    assert d18["command"].startswith("apcg figure 18 --model ")
    assert d19["command"].endswith(f"--pairs 30 --seed 0 -o {tmp_path / 'f19.png'}")


def test_fd_depth_encoder_and_distance(data, tmp_path):
    from training.fd_depth import fd_depth, frechet_distance, load_encoder, train_encoder
    rng = np.random.default_rng(0)
    a = rng.standard_normal((400, 5))
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    # two Gaussians with the same covariance: the distance is the squared mean shift
    shift = np.array([2.0, 0, 0, 0, 0])
    b = rng.standard_normal((200_000, 5))
    c = rng.standard_normal((200_000, 5)) + shift
    assert frechet_distance(b, c) == pytest.approx(4.0, rel=0.02)
    meta = train_encoder(data, tmp_path / "enc", epochs=3, progress=False)
    assert meta["test_accuracy_type"] > 0.8 > meta["chance"]  # A320neo vs Mavic 3
    enc_dir = tmp_path / "enc"
    assert meta["command"] == f"apcg fd-depth train --data {data} -o {enc_dir} --epochs 3 --seed 0"
    enc = load_encoder(tmp_path / "enc")
    cfg = config_from("tiny", steps=1, width=0.0625, checkpoint_every=1000, seed=10)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    untrained = APCGModel(export_model(tmp_path / "run", tmp_path / "m"), runtime="onnx")
    score = fd_depth(enc, untrained, data, n_pairs=40)
    assert score["fd_depth"] > score["fd_depth_real_halves"] >= 0.0


def test_ablation_runs_all_eight_variants_under_one_budget(data, tmp_path):
    from training.ablation import NO_NORM, VARIANTS, run_ablation, variant_name
    rep = run_ablation(data, tmp_path / "abl", steps=2, width=0.0625, pairs=20,
                       progress=False, encoder_epochs=1)
    assert len(VARIANTS) == 8 and len({variant_name(v) for v in VARIANTS + [NO_NORM]}) == 9
    assert [r["variant"] for r in rep["rows"]] == [variant_name(v) for v in VARIANTS + [NO_NORM]]
    nonorm = json.loads((tmp_path / "abl" / "tconv-attn-wgan-nonorm" / "model" /
                         "model.json").read_text())
    assert nonorm["norm"] is False and rep["rows"][-1]["norm"] is False
    assert all(r["norm"] for r in rep["rows"][:8])
    from apcg_core.families.cgan import APCGModel
    TAUS = APCGModel.TAUS
    for r in rep["rows"]:  # each variant's own tau, chosen on the validation half
        saved_model = json.loads((tmp_path / "abl" / r["variant"] / "model" / "model.json")
                                 .read_text())
        assert r["tau"] in TAUS and saved_model["tau"] == r["tau"]
        assert r["mmd_untrained"] is not None and r["jsd_untrained"] is not None
    assert rep["command"] == (f"apcg ablation --data {data} -o {tmp_path / 'abl'} --steps 2 "
                              "--width 0.0625 --pairs 20 --seed 0")
    assert all(r["steps"] == 2 and r["fd_depth"] >= 0 for r in rep["rows"])
    fc = next(r for r in rep["rows"] if r["variant"] == "fc-noattn-bce")
    saved = json.loads((tmp_path / "abl" / "fc-noattn-bce" / "train_config.json").read_text())
    assert saved["train"]["conv"] is False and saved["train"]["loss"] == "bce"
    assert saved["train"]["attention"] is False and fc["loss"] == "bce"
    table = (tmp_path / "abl" / "table3.md").read_text()
    assert "| no (FC) | no | no (BCE) | yes |" in table and "| yes | yes | yes | no |" in table
    again = run_ablation(data, tmp_path / "abl", steps=2, width=0.0625, pairs=20,
                         progress=False)  # finished runs are scored, not retrained
    assert [r["steps"] for r in again["rows"]] == [2] * 9


@pytest.mark.parametrize("family", ["point-gan", "voxel-gan", "diffusion"])
def test_comparison_families_train_resume_export_and_generate(data, tmp_path, family):
    from apcg_core.families import load_model as load_any
    from apcg_core.families.baselines import BaselineModel
    cfg = config_from("tiny", steps=4, checkpoint_every=2, seed=11, family=family,
                      n_points=64, voxel_res=16, diffusion_steps=20)
    full = Trainer(data, tmp_path / "full", cfg, progress=False)
    full.fit()
    part = Trainer(data, tmp_path / "part", replace(cfg, steps=2), progress=False)
    part.fit()
    again = Trainer(data, tmp_path / "part", cfg, resume=True, progress=False)
    again.fit()  # the same checkpoint / resume machinery as the cGAN: exactly the same run
    assert _losses(tmp_path / "full") == _losses(tmp_path / "part")
    model = load_any(export_model(tmp_path / "full", tmp_path / "m"))
    assert isinstance(model, BaselineModel) and model.meta["family"] == family
    ds = DepthDataset(data, "test")
    res = model.generate(ds.condition_rows(np.arange(5)), count=2, seed=3)
    assert len(res.table) == 10 and res.cloud.sample.max() <= 9
    if len(res.cloud):  # points sit on the lidar's cells, one per cell and sample
        keys = set(zip(res.cloud.sample.tolist(), res.cloud.cell_w.tolist(),
                       res.cloud.cell_h.tolist(), strict=True))
        assert len(keys) == len(res.cloud)
        r = res.cloud.range_m / model.lidar.r_r
        assert np.allclose(r - np.floor(r), 0.5, atol=1e-6)  # quantized ranges
    again_res = model.generate(ds.condition_rows(np.arange(5)), count=2, seed=3)
    assert np.array_equal(res.cloud.xyz, again_res.cloud.xyz)  # seeded


def test_training_memory_is_the_child_process_own_peak(data):
    from dataclasses import asdict

    from training.compare import training_memory
    ballast = np.ones(2 * 2**30 // 8)  # 2 GiB held (and touched) by this process at the fork
    small = training_memory(asdict(config_from("tiny", width=0.0625)), data, 1)
    assert ballast[-1] == 1.0
    assert 50 < small["peak_rss_mb"] < 1500, small  # not the parent's 2 GiB


def test_compare_lists_every_method_with_budget_memory_speed_and_bands(data, tmp_path):
    from apcg_core.families import load_model as load_any
    from training.compare import compare, markdown, method_names, write
    runs = {}
    for name, family, steps in (("cgan", "cgan", 3), ("point-gan", "point-gan", 2)):
        cfg = config_from("tiny", steps=steps, width=0.0625, seed=12, family=family,
                          n_points=64)
        Trainer(data, tmp_path / name, cfg, progress=False).fit()
        runs[name] = str(export_model(tmp_path / name, tmp_path / "models" / name))
    models = [(n, load_any(p)) for n, p in method_names([tmp_path / "models" / n for n in runs])]
    rep = compare(models, data, n_pairs=12, memory_steps=1)
    rep["command"] = "apcg compare ..."
    assert [r["method"] for r in rep["rows"]] == ["cgan", "point-gan"]
    for r, steps in zip(rep["rows"], (3, 2), strict=True):
        assert r["budget"]["steps"] == steps and r["budget"]["hours"] > 0
        assert r["training_memory"]["peak_rss_mb"] > 50  # a real torch process
        assert r["ms_per_cloud"] > 0
        assert sum(b["pairs"] for b in r["bands"].values()) == rep["pairs"]
        assert all("untrained" in b for b in r["bands"].values())
        scored = [b["mmd"] for b in r["bands"].values() if b["mmd"] is not None]
        assert r["mean"]["mmd"] == pytest.approx(np.mean(scored))
    # the same pairs for every method
    assert rep["rows"][0]["bands"].keys() == rep["rows"][1]["bands"].keys()
    md = markdown(rep)
    assert "| cgan | 3 |" in md and "| point-gan | 2 |" in md
    points = md.split("Points per cloud")[1]  # the counts the metrics do not see, per band
    for r in rep["rows"]:
        line = next(ln for ln in points.splitlines() if ln.startswith(f"| {r['method']} |"))
        assert line.count(" / ") == len(r["bands"])
        for b in r["bands"].values():
            assert f"| {b['points_generated']:.0f} / {b['points_standard']:.0f} " in line + " "
    out = write(rep, tmp_path / "report")
    assert (out / "compare.png").stat().st_size > 0
    with pytest.raises(InputError, match="must have different names"):
        method_names(["a/cgan", "b/cgan"])
