"""The training commands against damaged files, resumes with other settings and values at the
edges: every refusal one InputError (exit 2, one line) naming the value and what is accepted,
and every resume a command's own messages suggest works. Real torch, real commands, tiny sizes.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from apcg_core.errors import InputError
from apcg_core.families import default_model_dir

torch = pytest.importorskip("torch")

from training.distill import DistillConfig, distill  # noqa: E402
from training.fd_depth import DepthEncoder, load_encoder, train_encoder  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TEACHER = default_model_dir()
TINY = dict(width=0.25, steps=4, batch_size=4, checkpoint_every=2)


def apcg(*args, cwd=ROOT, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "apcg_core.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout)


def refused(res, *words):
    """The command was refused by name: exit 2, one error line holding ``words``, no
    traceback."""
    assert res.returncode == 2, (res.returncode, res.stderr[-3000:])
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    errors = [line for line in res.stderr.splitlines() if ": error: " in line]
    assert len(errors) == 1, res.stderr[-3000:]
    for w in words:
        assert w in errors[0], (w, errors[0])
    return errors[0]


def tiny_cfg(**over) -> DistillConfig:
    return DistillConfig(**{"teacher": str(TEACHER), **TINY, **over})


@pytest.fixture(scope="module")
def distilled(tmp_path_factory) -> Path:
    """A finished tiny distillation run (its checkpoint is what the damaged copies start
    from)."""
    run = tmp_path_factory.mktemp("distilled") / "run"
    distill(TEACHER, run, tiny_cfg(), device="cpu", progress=False)
    return run


def damaged_copies(src: Path, dest: Path) -> dict[str, Path]:
    """Copies of the torch file ``src``, each damaged another way."""
    dest.mkdir(parents=True, exist_ok=True)
    data = src.read_bytes()
    out = {}
    for name, content in (("truncated", data[: len(data) // 3]), ("empty", b""),
                          ("text", b"not a torch file\n")):
        out[name] = dest / f"{name}.pt"
        out[name].write_bytes(content)
    out["train"] = dest / "train.pt"  # what `apcg train` writes: another project file
    torch.save({"step": 3, "train": {"steps": 3}, "G": {}, "net": {}}, out["train"])
    out["tensor"] = dest / "tensor.pt"
    torch.save(torch.zeros(3), out["tensor"])
    return out


# --- A: every torch file a command reads is named when it cannot be used --------------------

def test_a_damaged_distill_checkpoint_is_named_on_resume(distilled, tmp_path):
    bad = damaged_copies(distilled / "checkpoint.pt", tmp_path / "bad")
    for kind, path in bad.items():
        run = tmp_path / f"run-{kind}"
        run.mkdir()
        for name in ("distill_config.json", "log.csv"):
            (run / name).write_bytes((distilled / name).read_bytes())
        (run / "checkpoint.pt").write_bytes(path.read_bytes())
        with pytest.raises(InputError, match=re.escape(str(run / "checkpoint.pt"))) as exc:
            distill(TEACHER, run, tiny_cfg(steps=6), device="cpu", resume=True, progress=False)
        message = str(exc.value)
        assert "\n" not in message
        expected = {"truncated": "cannot be read as an `apcg distill` checkpoint",
                    "text": "cannot be read as an `apcg distill` checkpoint",
                    "empty": "is empty (0 bytes)",
                    "train": "holds a checkpoint of `apcg train`",
                    "tensor": "holds a torch.Tensor"}[kind]
        assert expected in message, message
        assert (run / "checkpoint.pt").read_bytes() == path.read_bytes()  # left as it was


def test_a_the_command_line_names_a_truncated_checkpoint_and_a_train_run(distilled, tmp_path):
    run = tmp_path / "cut"
    run.mkdir()
    for name in ("distill_config.json", "log.csv"):
        (run / name).write_bytes((distilled / name).read_bytes())
    data = (distilled / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(data[:1000])
    refused(apcg("distill", "--teacher", TEACHER, "-o", run, "--steps", 5, "--batch-size", 4,
                 "--width", 0.25, "--checkpoint-every", 2, "--resume", "--device", "cpu"),
            "checkpoint.pt", "cannot be read as an `apcg distill` checkpoint")
    # a run of `apcg train` given to distill --resume --force: named, not KeyError 'config'
    train_run = tmp_path / "train_run"
    train_run.mkdir()
    torch.save({"step": 3, "train": {"steps": 3}, "G": {}, "net": {}},
               train_run / "checkpoint.pt")
    refused(apcg("distill", "-o", train_run, "--resume", "--force", "--device", "cpu"),
            "holds a checkpoint of `apcg train`", "not an `apcg distill` checkpoint")


def encoder_file(directory: Path, n_types: int = 2, shape=(16, 64)) -> Path:
    """What `apcg fd-depth train` writes (an untrained encoder: its bytes are the same kind)."""
    directory.mkdir(parents=True, exist_ok=True)
    torch.save({"state": DepthEncoder(n_types, *shape).state_dict(), "n_types": n_types,
                "shape": list(shape)}, directory / "encoder.pt")
    return directory


def test_a_damaged_or_foreign_encoders_are_named(tmp_path, distilled):
    good = encoder_file(tmp_path / "good")
    assert load_encoder(good).shape == (16, 64)
    bad = damaged_copies(good / "encoder.pt", tmp_path / "bad")
    bad["distill"] = distilled / "checkpoint.pt"
    expected = {"truncated": "cannot be read as an FD-depth encoder",
                "text": "cannot be read as an FD-depth encoder",
                "empty": "is empty (0 bytes)", "train": "holds a checkpoint of `apcg train`",
                "tensor": "holds a torch.Tensor", "distill": "holds a checkpoint of `apcg "
                                                          "distill`"}
    for kind, path in bad.items():
        enc = tmp_path / f"enc-{kind}"
        enc.mkdir()
        (enc / "encoder.pt").write_bytes(path.read_bytes())
        with pytest.raises(InputError, match=re.escape(str(enc / "encoder.pt"))) as exc:
            load_encoder(enc)
        assert expected[kind] in str(exc.value), str(exc.value)
    # the header and the weights disagree, or the header is no encoder's
    enc = tmp_path / "mismatch"
    enc.mkdir()
    torch.save({"state": DepthEncoder(3).state_dict(), "n_types": 2, "shape": [64, 256]},
               enc / "encoder.pt")
    with pytest.raises(InputError, match="do not fit the encoder of 2 types"):
        load_encoder(enc)
    torch.save({"state": {}, "n_types": "two", "shape": [64]}, enc / "encoder.pt")
    with pytest.raises(InputError, match="describes no encoder: n_types 'two'"):
        load_encoder(enc)
    # the command line: one line, exit 2
    (tmp_path / "cli").mkdir()
    (tmp_path / "cli" / "encoder.pt").write_bytes(bad["truncated"].read_bytes())
    refused(apcg("fd-depth", "score", "--encoder", tmp_path / "cli", "--data", tmp_path / "x"),
            "encoder.pt", "cannot be read as an FD-depth encoder")


def test_a_the_reader_loads_no_code(tmp_path):
    """A pickle that would run code on loading is refused as not this project's file."""
    from training.distill import read_torch_state
    marker = tmp_path / "ran"

    class Boom:
        def __reduce__(self):
            return (Path.touch, (marker,))

    torch.save({"state": Boom(), "n_types": 2, "shape": [16, 64]}, tmp_path / "evil.pt")
    with pytest.raises(InputError, match="cannot be read as an encoder"):
        read_torch_state(tmp_path / "evil.pt", "an encoder", ("state",), "`x`")
    assert not marker.exists()


# --- B: distill --resume does what its messages say ------------------------------------------

def _tiny_args(run, teacher=TEACHER, *extra):
    return ["distill", "--teacher", teacher, "-o", run, "--width", 0.25, "--steps", 6,
            "--batch-size", 4, "--checkpoint-every", 2, "--device", "cpu", "--no-progress",
            *extra]


def test_b_after_ctrl_c_the_printed_commands_resume_the_run(tmp_path, hold):
    """Ctrl-C, then exactly the command the message prints; and the hint's own way (the same
    command + --resume, the teacher spelled another way, a longer run)."""
    for way in ("printed", "same-command"):
        work = tmp_path / way
        teacher = work / "teacher"
        teacher.parent.mkdir()
        teacher.symlink_to(TEACHER, target_is_directory=True)
        run = work / "run"
        proc = subprocess.Popen([sys.executable, "-m", "apcg_core.cli",
                                 *map(str, _tiny_args(run, teacher))],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                cwd=ROOT, env=hold.env("distill.checkpoint-written"))
        hold.wait("distill.checkpoint-written", proc)
        proc.send_signal(signal.SIGINT)
        hold.release("distill.checkpoint-written")
        _, err = proc.communicate(timeout=120)
        hold = type(hold)(hold.directory.parent / f"points-{way}")  # a fresh set of points
        assert proc.returncode == 130, err
        assert "goes on from the checkpoint at step 2" in err, err[-2000:]
        if way == "printed":
            printed = re.search(r"`(apcg distill [^`]*)`", err).group(1)
            again = apcg(*shlex.split(printed)[1:], "--no-progress", "--device", "cpu")
        else:
            hint = err.strip().splitlines()[-1]
            assert "Add --resume to the same command" in hint, hint
            # the same command, the teacher by another name of the same directory (the link's
            # target, not the link), the run relative to another directory, 8 steps
            args = _tiny_args(Path(os.path.relpath(run, work)), TEACHER, "--resume")
            args[args.index("--steps") + 1] = 8
            again = apcg(*args, cwd=work)
        assert again.returncode == 0, again.stderr[-3000:]
        state = torch.load(run / "checkpoint.pt", weights_only=True)
        assert state["step"] == (6 if way == "printed" else 8)
        assert state["config"]["batch_size"] == 4 and state["config"]["width"] == 0.25
        assert (run / "model" / "model.json").is_file()


def test_b_resume_refuses_only_the_settings_that_define_the_run(tmp_path):
    run = tmp_path / "run"
    distill(TEACHER, run, tiny_cfg(steps=2), device="cpu", progress=False)
    for over, word in ((dict(seed=1), "--seed 1 (the run's: 0)"),
                       (dict(batch_size=8), "--batch-size 8 (the run's: 4)"),
                       (dict(width=0.5), "--width 0.5 (the run's: 0.25)"),
                       (dict(teacher=str(ROOT / "apcg_core" / "models" / "cgan")),
                        "--teacher")):
        with pytest.raises(InputError, match=re.escape(word)):
            distill(TEACHER, run, tiny_cfg(steps=4, **over), device="cpu", resume=True,
                    progress=False)
    # the run's length and time cap may change, as `apcg train` lets them
    out = distill(TEACHER, run, tiny_cfg(steps=4, minutes=5.0, checkpoint_every=1),
                  device="cpu", resume=True, progress=False)
    assert out["steps"] == 4
    with pytest.raises(InputError, match="--steps 3: the run .* is at step 4"):
        distill(TEACHER, run, tiny_cfg(steps=3), device="cpu", resume=True, progress=False)
    # on the command line a resume with settings left out takes the run's
    res = apcg("distill", "--resume", "-o", run, "--steps", 5, "--device", "cpu",
               "--no-progress")
    assert res.returncode == 0, res.stderr[-3000:]
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    assert st["step"] == 5 and st["config"]["seed"] == 0 and st["config"]["width"] == 0.25
    refused(apcg("distill", "--resume", "-o", run, "--seed", 3, "--device", "cpu"),
            "--seed 3 (the run's: 0)")


# --- C: an encoder's epochs are bounded ------------------------------------------------------

def test_c_fd_depth_train_refuses_epochs_it_cannot_count(tiny_training_data, tmp_path):
    for bad in (1e308, float("inf"), float("nan"), 0.0, -1.0, 1001, True):
        with pytest.raises(InputError, match="epochs .* not accepted: a number > 0 and <= 1000"):
            train_encoder(tiny_training_data, tmp_path / "enc", epochs=bad, progress=False)
    assert not (tmp_path / "enc").exists()
    refused(apcg("fd-depth", "train", "--data", tiny_training_data, "-o", tmp_path / "enc",
                 "--epochs", "1e308"), "--epochs 1e+308", "<= 1000")
    assert not (tmp_path / "enc").exists()


# --- D: a stopped ablation resumes; with other settings it is refused by name ----------------

def test_d_a_record_pattern_with_a_wildcard_directory_marks_the_jobs_own_files(tmp_path):
    """The output guard's record of a resumable job (``*/train_config.json``: the ablation's
    runs) is found in any subdirectory, so the job's own files are its to replace; a layout
    without it stays refused."""
    from apcg_core.cli import build_parser
    from apcg_core.outputs import Guard, _has_record
    out = tmp_path / "abl"
    args = build_parser(None, "ablation").parse_args(
        ["ablation", "--data", str(tmp_path), "-o", str(out), "--encoder", str(tmp_path)])
    mine = out / "tconv-attn-wgan" / "train_config.json"
    mine.parent.mkdir(parents=True)
    (out / "notes.txt").write_text("a user's file")
    mine.write_text("{}")
    assert Guard(args).refusal(mine) is None  # the run's own record, rewritten on resume
    assert Guard(args).refusal(out / "notes.txt") is None  # inside the job's directory
    elsewhere = tmp_path / "other"
    (elsewhere / "deep" / "run").mkdir(parents=True)
    (elsewhere / "deep" / "run" / "train_config.json").write_text("{}")
    (elsewhere / ".hidden").mkdir()
    (elsewhere / ".hidden" / "x.json").write_text("{}")
    assert _has_record(str(elsewhere), ("*/*/train_config.json",))
    assert not _has_record(str(elsewhere), ("*/train_config.json",))  # one level only
    assert _has_record(str(elsewhere), ("*/x.json",))  # names starting with a dot too
    assert _has_record(str(elsewhere), ("deep/r?n/train_config.json",))
    assert not _has_record(str(elsewhere), ("deep/*/missing.json", "nothing/*"))
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("a user's file")
    args = build_parser(None, "ablation").parse_args(
        ["ablation", "--data", str(tmp_path / "x"), "-o", str(tmp_path / "plain")])
    assert "already exists" in Guard(args).refusal(tmp_path / "plain" / "notes.txt")


def _tiny_encoder(directory: Path) -> Path:
    encoder_file(directory, 2, (16, 64))
    (directory / "encoder.json").write_text(json.dumps(
        {"test_accuracy_type": 0.5, "chance": 0.5, "seed": 0}))
    return directory


def test_d_a_stopped_ablation_resumes_from_the_command_line(tiny_training_data, tmp_path):
    """An ablation stopped after its first variant (made here by the API, as a stopped run
    leaves it) goes on with the same command: its first run is the job's own."""
    from training.ablation import VARIANTS, run_ablation, variant_name
    enc = _tiny_encoder(tmp_path / "enc")
    out = tmp_path / "abl"
    run_ablation(tiny_training_data, out, steps=1, width=0.0625, pairs=4, encoder=enc,
                 progress=False, variants=VARIANTS[:1], no_norm=False)
    first = out / variant_name(VARIANTS[0])
    assert [p.name for p in out.iterdir() if p.is_dir()] == [first.name]
    before = (first / "checkpoint.pt").read_bytes()
    res = apcg("ablation", "--data", tiny_training_data, "-o", out, "--steps", 1, "--width",
               0.0625, "--pairs", 4, "--encoder", enc, "--skip-no-norm", timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads((out / "table3.json").read_text())["rows"]
    assert [r["variant"] for r in rows] == [variant_name(v) for v in VARIANTS]
    assert (first / "checkpoint.pt").read_bytes() == before  # finished: scored, not retrained


def test_d_an_ablation_resumed_with_other_settings_is_refused_naming_them(tiny_training_data,
                                                                          tmp_path):
    import shutil

    from training.ablation import VARIANTS, run_ablation
    enc = _tiny_encoder(tmp_path / "enc")
    out = tmp_path / "abl"
    kw = dict(steps=1, width=0.0625, pairs=4, encoder=enc, progress=False,
              variants=VARIANTS[:1], no_norm=False)
    run_ablation(tiny_training_data, out, **kw)
    files = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    other_data = tmp_path / "copy-of-data"
    shutil.copytree(tiny_training_data, other_data)
    for over, words in ((dict(seed=1), ["--seed 1", "0)"]),
                        (dict(width=0.125), ["--width 0.125", "0.0625)"]),
                        (dict(data=other_data), ["--data", str(tiny_training_data)])):
        args = {**kw, **over}
        data = args.pop("data", tiny_training_data)
        with pytest.raises(InputError, match="started with other settings") as exc:
            run_ablation(data, out, **args)
        assert all(w in str(exc.value) for w in words), str(exc.value)
    # refused before any work: nothing of the runs changed
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == files
    # the ablation's own encoder, trained with another seed, is named too
    own = tmp_path / "own"
    (own / "encoder").mkdir(parents=True)
    _tiny_encoder(own / "encoder")
    with pytest.raises(InputError, match=r"--seed 2 \(the run's in .*encoder: 0\)"):
        run_ablation(tiny_training_data, own, **{**kw, "encoder": None, "seed": 2})
    # a given encoder that cannot be read is named before any training
    (tmp_path / "badenc").mkdir()
    (tmp_path / "badenc" / "encoder.json").write_text("{}")
    with pytest.raises(InputError, match="encoder.json is not an FD-depth encoder's record"):
        run_ablation(tiny_training_data, tmp_path / "abl2", **{**kw, "encoder":
                                                               tmp_path / "badenc"})
    assert not (tmp_path / "abl2").exists()


# --- E: choose-tau scores, reports and writes the exact thresholds ---------------------------

def test_e_choose_tau_keys_and_applies_the_exact_value_scored(tiny_training_data, tmp_path):
    import shutil
    model = tmp_path / "m"
    shutil.copytree(TEACHER, model)
    res = apcg("choose-tau", "--model", model, "--data", tiny_training_data, "--pairs", 4,
               "--taus", "0.1234561,0.1234564,0.1234561", "--apply", "-o",
               tmp_path / "sweep.json")
    assert res.returncode == 0, res.stderr[-3000:]
    sweep = json.loads((tmp_path / "sweep.json").read_text())
    assert list(sweep["taus"]) == ["0.1234561", "0.1234564"]  # each scored once, told apart
    assert all(float(k) in (0.1234561, 0.1234564) for k in sweep["taus"])
    written = json.loads((model / "model.json").read_text())["tau"]
    assert written == sweep["best"] and written in (0.1234561, 0.1234564)
    # the model's own candidates keep their short keys
    from apcg_core.families import load_model
    from training.protocol import choose_tau, tau_key
    assert [tau_key(t) for t in (-1.0, 0.5, 3.0, 0.1 + 0.2)] == ["-1", "0.5", "3",
                                                                 "0.30000000000000004"]
    plus = load_model(model, runtime="onnx")
    rep = choose_tau(plus, tiny_training_data, taus=[0.25, 1 / 3], n_pairs=4)
    assert rep["best"] in (0.25, 1 / 3) and {float(k) for k in rep["taus"]} == {0.25, 1 / 3}


def test_e_every_tau_is_checked_before_any_is_scored(tiny_training_data, tmp_path):
    from apcg_core.families import load_model
    from training.protocol import choose_tau
    cgan = load_model(ROOT / "apcg_core" / "models" / "cgan", runtime="onnx")
    # a dataset that does not exist: nothing is read (or scored) before the thresholds pass
    for taus, word in (((0.5, 2.0), "tau = 2.0 is out of range"),
                       ((-0.5, float("nan")), "tau must be finite, got nan"),
                       ((), "no candidate thresholds")):
        with pytest.raises(InputError, match=re.escape(word)):
            choose_tau(cgan, tmp_path / "no-data", taus=taus, n_pairs=4)
    refused(apcg("choose-tau", "--model", ROOT / "apcg_core" / "models" / "cgan", "--data",
                 tiny_training_data, "--pairs", 4, "--taus", "0.5,2"),
            "tau = 2.0 is out of range", "no threshold was scored")


# --- F: teach takes a type by name, and its time budget says what it bounds ------------------

def test_f_teach_refuses_a_bare_number_for_a_type(tmp_path):
    from training.teach import teach
    for key in ("5", " 5 ", "+5", "-1", "0005", "99999", 5, True, 5.0):
        with pytest.raises(InputError, match="name") as exc:
            teach(TEACHER, key, tmp_path / "out", samples=8, steps=1, progress=False)
        assert "\n" not in str(exc.value)
    with pytest.raises(InputError, match=r"the type at index 5 is '737-700'"):
        teach(TEACHER, "5", tmp_path / "out", samples=8, steps=1, progress=False)
    assert not (tmp_path / "out").exists()
    refused(apcg("teach", "--model", TEACHER, "--type", "5", "-o", tmp_path / "out",
                 "--samples", 8, "--steps", 1), "--type '5' is a number, not a type's name",
            "by name")
    assert not (tmp_path / "out").exists()


def test_f_teach_keeps_to_its_budget_or_says_it_cannot(tiny_training_data, tmp_path):
    from training.export import export_model
    from training.teach import MIN_MINUTES, teach
    from training.trainer import Trainer, config_from
    for minutes in (0.01, 0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="--minutes"):
            teach(TEACHER, "777-300ER", tmp_path / "out", samples=8, steps=1,
                  minutes=minutes, progress=False)
    assert not (tmp_path / "out").exists()
    # a small model of two types (the tiny window), taught a third within the least budget
    cfg = config_from("tiny", family="apcg-plus", steps=2, seed=3, width=0.25, sheet=32,
                      checkpoint_every=10**6, log_every=1)
    Trainer(tiny_training_data, tmp_path / "run", cfg, progress=False).fit()
    model = export_model(tmp_path / "run", tmp_path / "model")
    rep = teach(model, "777-300ER", tmp_path / "out", samples=8, steps=1, minutes=MIN_MINUTES,
                progress=False)
    sec, budget = rep["seconds"], rep["budget"]
    assert budget["minutes"] == MIN_MINUTES and budget["counts"] == "dataset and fit"
    assert budget["kept"] == (sec["dataset"] + sec["fit"] <= 60 * MIN_MINUTES + 0.02)
    assert sec["total"] == pytest.approx(sec["dataset"] + sec["fit"] + sec["score"], abs=0.05)
    assert json.loads((tmp_path / "out" / "teach.json").read_text())["budget"] == budget
