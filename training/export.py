"""A training run's checkpoint -> a model directory (model.json + what its family stores:
generator.onnx for the cGAN, weights.pt + counts.npz for the comparison families)."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import torch

from apcg_core.depth import TAU_DEFAULT
from apcg_core.errors import InputError
from apcg_core.families import get_family
from apcg_core.families.registry import MODEL_FORMAT, MODEL_FORMAT_VERSION
from apcg_core.io.atomic import atomic_path
from apcg_core.io.dataset import read_header
from apcg_core.nn.cgan import COND_DIM, NOISE_DIM, Generator
from apcg_core.typetable import TypeTable

from .trainer import check_same_dataset, read_checkpoint, read_run_record


def ordinal(n: int) -> str:
    """2 -> "2nd", 100 -> "100th", 13 -> "13th" (the log note's English)."""
    suffix = "th" if n % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"

def export_onnx(g: Generator, path: Path) -> None:
    g = g.eval()
    z = torch.zeros(2, NOISE_DIM)
    nu = torch.zeros(2, COND_DIM)
    with warnings.catch_warnings(), atomic_path(path) as tmp:
        warnings.simplefilter("ignore")
        torch.onnx.export(g, (z, nu), str(tmp), input_names=["noise", "nu"],
                          output_names=["image"], opset_version=17, dynamo=False,
                          do_constant_folding=False,
                          dynamic_axes={"noise": {0: "batch"}, "nu": {0: "batch"},
                                        "image": {0: "batch"}})


def export_model(run_dir, out_dir, tau: float | None = None, data_dir=None,
                 checkpoint=None, raw: bool = False, sampling_steps: int | None = None,
                 log_every: int = 1, force: bool = False) -> Path:
    """Export a run as a model directory (see :func:`_export`). The model is written into a
    hidden staging directory beside ``out_dir`` and published into it file by file when
    complete (``apcg_core.outputs.staged_directory``: each file whole, none on failure or
    Ctrl-C). An ``out_dir`` that holds anything is refused unless ``force``; then the files of
    the model replace those of the same names, and nothing else there is touched (a directory
    is never deleted). Everything is checked before anything is written: the run directory,
    the dataset it trained on and what its family's export reads are inputs (never -o, nor
    around it), and a ``checkpoint`` must be the run's own."""
    from apcg_core.errors import check_int
    check_int("log_every", log_every, 1)
    run, out = Path(run_dir), Path(out_dir)
    if out.resolve() == run.resolve():
        raise InputError(f"-o {out} is the run directory itself; export to another directory")
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out} is a file, not a directory")
    job = _read_run(run, checkpoint, data_dir)
    _refuse_inputs(out, [job["data"]])  # --run: the command's own input
    _refuse_inputs(out, job["reads"], "the model this run was trained from (its --init), an "
                                      "input of this export")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise InputError(f"-o {out} already holds files; choose a new directory, or --force to "
                         "replace it")
    from apcg_core.outputs import staged_directory
    with staged_directory(out) as staging:
        _export(run, staging, tau, data_dir, checkpoint, raw, sampling_steps, log_every,
                job=job)
        _loads_back(staging, out)
    return out


def _loads_back(staging: Path, out: Path) -> None:
    """The staged model opened as `apcg generate --model` opens it, before it is published:
    a model the loader would refuse (a threshold out of its family's range, a record a
    damaged dataset gave it) is never written."""
    from apcg_core.families import load_model
    try:
        load_model(staging)
    except InputError as exc:
        raise InputError("the model this export would write is one apcg cannot open: "
                         + str(exc).replace(str(staging), str(out))) from None


def _refuse_inputs(out: Path, inputs, what: str = "an input of this export") -> None:
    """-o is, or lies inside, none of ``inputs`` (the one rule, apcg_core.outputs), inside a
    command as outside one; ``what`` says what they are."""
    from apcg_core.outputs import active, add_inputs, real, where_inputs
    if not inputs:
        return
    if active() is not None:
        add_inputs(inputs, what)
        return
    why = where_inputs("-o", out, [real(p) for p in inputs if Path(p).exists()])
    if why:
        raise InputError(why.replace("an input of this command", what))


def _read_run(run: Path, checkpoint=None, data_dir=None) -> dict:
    """The run's checkpoint (the latest, or ``checkpoint``, which must be the run's own: in
    the run directory, of the run's family, network and settings), its record, the dataset it
    trained on and the family that exports it."""
    ck = Path(checkpoint) if checkpoint else run / "checkpoint.pt"
    if not ck.exists():
        raise InputError(f"{ck} does not exist: nothing to export")
    st = read_checkpoint(ck)
    record = read_run_record(run)
    if record is None and data_dir is None:
        raise InputError(f"{run} has no train_config.json to say which dataset it trained on")
    if checkpoint:
        _check_own_checkpoint(run, ck, st, record)
    family = get_family(st["train"].get("family", "cgan"), need="export")
    reads = list(getattr(family, "export_reads", lambda state: [])(st))
    data = data_dir or record["data"]
    head = read_header(data)
    if record is not None:  # before anything is written: the dataset the run learnt, or none
        check_same_dataset(record, head, data, "export", run=run)
    return {"checkpoint": ck, "state": st, "record": record, "family": family,
            "data": data, "head": head, "reads": reads}


def _check_own_checkpoint(run: Path, ck: Path, st: dict, record: dict | None) -> None:
    from apcg_core.outputs import real

    from .trainer import RESUMABLE
    mine = real(run)
    if not real(ck).startswith(mine.rstrip("/") + "/"):
        raise InputError(f"--checkpoint {ck} is not in the run directory {run}; give one of "
                         f"the run's own ({run}/checkpoint.pt or {run}/checkpoints/*.pt), or "
                         "--run the run that wrote it")
    if record is None:
        return
    ran = record["train"]
    st_train = json.loads(json.dumps(st["train"], default=str))  # tuples as the record's lists
    differ = [k for k in sorted(set(st["train"]) | set(ran)) if k not in RESUMABLE
              and st_train.get(k) != ran.get(k)]
    net = json.loads(json.dumps(st.get("net"), default=str))
    if ("net" in record and net != record["net"]) or differ:
        what = ", ".join(f"{k} {st_train.get(k)!r} (the run's: {ran.get(k)!r})"
                         for k in differ[:4]) or "its network"
        raise InputError(f"--checkpoint {ck} is not {run}'s own: its {what} differ from the "
                         f"run's train_config.json; give the run that wrote it as --run")


def _export(run_dir, out_dir, tau: float | None = None, data_dir=None,
            checkpoint=None, raw: bool = False, sampling_steps: int | None = None,
            log_every: int = 1, job: dict | None = None) -> Path:
    """``checkpoint``: a kept copy (e.g. checkpoints/step-001000.pt) instead of the latest.
    The generator's moving average is exported when the run kept one, the raw weights when
    ``raw`` or when it did not. ``sampling_steps`` (families that sample on a schedule) records
    how many of the schedule's steps generation takes by default (fewer: faster, coarser); a
    family without a schedule refuses it. What the model directory holds is the run's family's
    (``training/families/<family>.py``); nothing is written when the family refuses.
    ``log_every`` keeps every n-th step of the log (and the last), for a model that ships in the
    package. ``job``: what :func:`_read_run` read (read here when not given)."""
    from apcg_core.errors import check_int
    check_int("log_every", log_every, 1)
    run = Path(run_dir)
    job = job or _read_run(run, checkpoint, data_dir)
    st, record, family, data = job["state"], job["record"], job["family"], job["data"]
    head = job["head"]  # checked against the run's record by _read_run
    averaged = st.get("G_ema") is not None and not raw
    if averaged:
        st["G"] = st["G_ema"]
    meta = {"format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION, "net": st["net"],
            "condition_space": head["condition_space"], "lidar": head["lidar"],
            "types": TypeTable.from_records(head["types"]).to_records(),
            "tau": getattr(family, "default_tau", TAU_DEFAULT) if tau is None else tau,
            "trained_steps": st["step"],
            "trained_epochs": trained_epochs(st, head, (record or {}).get("world", 1)),
            "dataset": head.get("name"), "train": st["train"],
            "norm": bool(st["train"].get("norm", True)),
            "generator_weights": (f"moving average (decay {st['train']['ema']:g}) since step "
                                  f"{st.get('ema_since', 0)}" if averaged else "raw")}
    if head.get("sensor") is not None:
        # trained on a sensor's photon clouds (the dataset was built with --sensor): the
        # model's clouds are that sensor's already; the header's sensor, as it recorded it
        meta["sensor"] = head["sensor"]
    out = family.export(st, head, Path(out_dir), meta, data, sampling_steps=sampling_steps)
    # a family that writes beside a model's own files names its run's record apart
    prefix = getattr(family, "record_prefix", "")
    if (run / "train_config.json").exists():
        shutil.copy(run / "train_config.json", out / f"{prefix}train_config.json")
    if (run / "log.csv").exists():  # the log up to the exported step
        from apcg_core.io.csv_table import read_csv
        table = read_csv(run / "log.csv", required=("step",), what="training log")
        rows = [r for r in table if r.int("step") <= st["step"]]
        keep = [r for r in rows[:-1] if r.int("step") % log_every == 0] + rows[-1:]
        lines = [table.header_line, *(r.line for r in keep)]
        (out / f"{prefix}log.csv").write_text(
            "".join(table.lines[i - 1].rstrip("\r\n") + "\n" for i in lines))
        if log_every > 1:
            meta_path = out / "model.json"
            meta_now = json.loads(meta_path.read_text())
            meta_now[f"{prefix}log"] = (f"{prefix}log.csv keeps every {ordinal(log_every)} of the "
                                        f"run's {len(rows)} logged steps, and the last")
            meta_path.write_text(json.dumps(meta_now, indent=1) + "\n")
    return out


def trained_epochs(state: dict, head: dict, world: int = 1) -> float:
    """Epochs over the training split (``head``: its dataset.json) that the checkpoint's
    batches made: with ``world`` processes (torchrun) each count of the batch counter is
    ``world`` batches, one per rank (the trainer's own ``batches_per_epoch``, from the
    header's count: the split itself need not be loaded)."""
    batch = state["train"]["batch_size"] * int(world)
    bpe = int(head["n_train"]) // batch
    if bpe < 1:
        raise InputError(f"{head['n_train']} samples are fewer than one batch of "
                         f"{state['train']['batch_size']} x {world} process(es)")
    return round(state["batch_counter"] / bpe, 3)
