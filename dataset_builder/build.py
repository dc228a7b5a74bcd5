"""Build a dataset: plan -> shards (one type each) -> manifest. Resumable and deterministic.

A shard's file appears under its final name only when complete (written to a ``.part`` file,
fsynced, renamed), so a build killed at any point and started again skips the finished shards
and remakes the rest; since every shard is a pure function of the plan, the result is byte for
byte the dataset of an uninterrupted run.

Builds of different ``--shard I/N`` parts may run at once into one directory (a job array):
every temporary file carries its writer's pid, files that several processes write (the plan
files, the manifest) have the same bytes whoever writes them and appear by atomic rename, and
a lock file per shard spec refuses a second build of the same part while the first one lives.

Where the shards are computed (this process, a local pool, a Dask cluster) is the engine's
business (``engine.py``); every engine runs the same ``shards.run_task`` on the same tasks. Ctrl-C
stops the workers, drops their temporary files and raises ``BuildInterrupted`` saying how many
shards are done: the same command resumes.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import time
from pathlib import Path

import numpy as np

from apcg_core import __version__
from apcg_core.errors import InputError
from apcg_core.io.dataset import (
    FORMAT_VERSION,
    Shard,
    check_complete,
    dataset_stamp,
    foreign_shard,
    json_bytes,
    load_shard,
    read_condition_index,
    read_header,
    read_manifest,
    sha256_file,
    write_atomic,
)
from apcg_core.lidar import DEG
from apcg_core.lock import ProcessLock, pid_alive
from apcg_core.progress import Progress

from .backends import check_backend
from .engine import RunSettings, get_engine, worker_init  # noqa: F401 (benches import it here)
from .plan import Plan, ShardPlan, check_plan, config_path, load_config, make_plan
from .rays import bounding_radius
from .shards import ShardTask, close_simulators, part_suffix, run_task


def header_of(plan: Plan, catalog) -> dict:
    cfg = plan.config
    return {
        "format": "apcg-dataset", "format_version": FORMAT_VERSION, "apcg_version": __version__,
        "name": cfg.get("name", ""), "config": cfg, "lidar": plan.lidar.to_dict(),
        "condition_space": plan.space.to_dict(),
        "types": [{"code": i, "name": t.name, "catalog_index": t.index, "kind": t.kind,
                   "range_band": t.range_band, "depth_length_m": catalog.depth_length_m(t),
                   "bounding_radius_m": bounding_radius(catalog.mesh(t).vertices)}
                  | catalog.mesh_record(t) for i, t in enumerate(plan.types)],
        "n_samples": plan.n_samples,
        "n_train": int((plan.split == "train").sum()), "n_test": int((plan.split == "test").sum()),
        "grid_values": plan.values,
        "shards": [{"index": s.index, "file": s.file, "split": s.split, "type_code": s.type_code,
                    "n_samples": len(s.rows)} for s in plan.shards],
        "conditions_file": "conditions.csv",
    } | (_photon_header(plan) if plan.sensor else {})


def header_difference(old: bytes, new: bytes) -> str:
    """What differs between two dataset.json headers, in words: the keys, and for the types
    which type and which of its records (its mesh, its length, ...)."""
    try:
        a, b = json.loads(old), json.loads(new)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return "it is not a dataset header"
    if not isinstance(a, dict):
        return "it is not a dataset header"
    keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    said = []
    for k in keys:
        if k == "types" and isinstance(a.get(k), list) and len(a[k]) == len(b[k]):
            for x, y in zip(a[k], b[k], strict=True):
                if isinstance(x, dict) and x != y:
                    fields = sorted(f for f in set(x) | set(y) if x.get(f) != y.get(f))
                    said.append(f"type {y.get('name')!r}: " + ", ".join(
                        f"{f} (its mesh changed in the catalog since)" if f == "mesh_sha256"
                        else f for f in fields))
        else:
            said.append(k)
    return "; ".join(said) or "its bytes"


def _photon_header(plan: Plan) -> dict:
    """What a photon dataset's header adds (an ideal one's header has none of it)."""
    from apcg_core.sensor import reflectivity_of
    return {"sensor": plan.sensor.to_dict(),
            "supersample": int(plan.config.get("supersample", 4)),
            "reflectivity": {t.name: reflectivity_of(t) for t in plan.types}}


def conditions_csv(plan: Plan) -> bytes:
    shard_of = np.empty(plan.n_samples, np.int64)
    for s in plan.shards:
        shard_of[s.rows] = s.index
    t = plan.table
    names = [ty.name.replace(",", " ") for ty in plan.types]
    lines = ["sample_id,split,shard,type_code,type_name,range_m,elevation_deg,pitch_deg,"
             "yaw_deg,roll_deg"]
    deg = t[:, 2:] / DEG
    for i in range(plan.n_samples):
        c = int(t[i, 0])
        lines.append(f"{i},{plan.split[i]},{shard_of[i]},{c},{names[c]},{t[i, 1]!r},"
                     f"{deg[i, 0]!r},{deg[i, 1]!r},{deg[i, 2]!r},{deg[i, 3]!r}")
    return ("\n".join(lines) + "\n").encode()


def _remove_dead_parts(directory: Path) -> None:
    """Delete ``NAME.PID.part`` files whose writer is gone (or is us); never a live writer's."""
    for part in directory.glob("*.part"):
        pid = part.name.rsplit(".", 2)[-2] if part.name.count(".") >= 2 else ""
        if not pid.isdigit() or int(pid) == os.getpid() or not pid_alive(int(pid)):
            try:
                part.unlink()
            except FileNotFoundError:
                pass


def parse_shard_spec(spec: str | None) -> tuple[int, int]:
    if spec is None:
        return 0, 1
    parts = str(spec).split("/")
    if len(parts) != 2 or not all(re.fullmatch(r"\s*-?[0-9]+\s*", p) for p in parts):
        # ASCII digits only: int() would also read '١' (an Arabic-Indic one)
        raise InputError(f"--shard takes I/N (e.g. 3/10), got {spec!r}")
    i, n = (int(x) for x in parts)
    if n < 1 or not 0 <= i < n:
        raise InputError(f"--shard {spec}: need N >= 1 and 0 <= I < N (I counts from 0)")
    return i, n


class BuildInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a build; the message says how far it got and how to resume. Still a
    KeyboardInterrupt, so a caller that does not handle it stops as on any Ctrl-C."""


def build_dataset(config: str | dict, out_dir, backend: str | None = None, workers: int = 1,
                  shard_spec: str | None = None, progress: bool = True,
                  tasks_per_process: int | None = None, catalog=None, engine: str = "local",
                  address: str | None = None, connect_timeout_s: float | None = None,
                  sensor: str | None = None, lidar: str | None = None, warn=None) -> dict:
    """Build (or resume) the dataset of ``config`` in ``out_dir``; returns a summary.
    ``warn(message)``, when given, hears a window too small for the plan's targets first.

    ``engine`` says where the shards are computed (``engine.ENGINES``: this machine, or a
    Dask cluster at ``address``, which must answer within ``connect_timeout_s``); the bytes
    written do not depend on it."""
    from apcg_core.catalog.catalog import default_catalog
    catalog = catalog or default_catalog()
    cfg = load_config(config) if isinstance(config, str) else dict(config)
    source = (f"dataset config {config_path(config)}" if isinstance(config, str)
              else "dataset config")
    if backend:
        check_backend(backend)
    # the whole plan, every condition, before anything is written or warned of
    plan = make_plan(cfg, catalog, backend, sensor, lidar, source=source)
    check_plan(plan, catalog, source)
    check_backend(plan.config["backend"])
    if warn is not None:  # before the work: a window too small for the plan's targets
        from apcg_core.plausibility import WINDOW_CHECK_ROWS, window_fit, window_warning
        # each type's nearest conditions (the largest in the window), WINDOW_CHECK_ROWS in all
        per = max(1, WINDOW_CHECK_ROWS // max(1, len(plan.types)))
        codes = plan.table[:, 0].astype(np.int64)
        rows = np.concatenate([np.flatnonzero(codes == c)[np.argsort(
            plan.table[codes == c, 1], kind="stable")[:per]] for c in np.unique(codes)])
        names = [plan.types[int(c)].name for c in plan.table[rows, 0]]
        warning = window_warning(plan.lidar, *window_fit(
            plan.lidar, lambda n: catalog.mesh(n).vertices, names, plan.table[rows]),
            "the config's nearest targets")
        if warning:
            warn(warning)
    if not isinstance(workers, int) or workers < 1:
        raise InputError(f"--workers must be an integer >= 1, got {workers!r}")
    part_i, part_n = parse_shard_spec(shard_spec)
    out = Path(out_dir)
    runner = get_engine(engine)
    settings = RunSettings(workers=workers, address=address, tasks_per_process=tasks_per_process,
                           output=str(out.resolve()), connect_timeout_s=connect_timeout_s)
    runner.check(settings)  # before anything is written: a bad address costs nothing
    (out / "shards").mkdir(parents=True, exist_ok=True)
    # One live build per shard spec and directory; parts of one build run side by side.
    lock = ProcessLock(out / f".build-{part_i}-of-{part_n}.lock",
                       f"build of --shard {part_i}/{part_n} into {out}")
    lock.acquire()
    try:
        summary = _build_locked(plan, catalog, out, runner, settings, part_i, part_n, progress)
    finally:
        lock.release()
    summary["n_samples"] = plan.n_samples
    summary["samples_outside_table1_bands"] = plan.n_outside_table1_bands()
    return summary


def _build_locked(plan: Plan, catalog, out: Path, runner, settings: RunSettings, part_i: int,
                  part_n: int, progress: bool) -> dict:
    header = json_bytes(header_of(plan, catalog))
    head = json.loads(header)  # as every reader reads it back
    table = conditions_csv(plan)  # once: about a second a 10^5 samples
    head_path = out / "dataset.json"
    # Concurrent builders of one plan write the same bytes here, each through its own
    # temporary file and an atomic rename, so any interleaving leaves complete, equal files.
    fresh = not head_path.exists()
    if not fresh:
        if (old := head_path.read_bytes()) != header:
            raise InputError(f"{out} already holds a different dataset (its dataset.json differs "
                             f"from this config's: {header_difference(old, header)}); "
                             "build into a new directory or delete it")
    elif stray := sorted((out / "shards").glob("*.npz")):
        # dataset.json is written before any shard: shards without it are of no known build
        # (copied in, or its dataset.json deleted), never to be taken in as this one's
        raise InputError(f"{out / 'shards'} holds {len(stray)} shard file(s) ({stray[0].name}"
                         f"{', ...' if len(stray) > 1 else ''}) but {out} has no dataset.json, "
                         "so nothing says which build made them; build into a new directory, "
                         "or delete them")
    if fresh:
        # first: the header is the record that makes the directory this build's own
        # (apcg_core.outputs), so a conditions.csv of ours never stands without it; a
        # conditions.csv missing beside it is made below (a build stopped in between)
        write_atomic(head_path, header, part_suffix=part_suffix())
        write_atomic(out / "conditions.csv", table, part_suffix=part_suffix())
    elif not (out / "conditions.csv").exists():
        write_atomic(out / "conditions.csv", table, part_suffix=part_suffix())
    elif (out / "conditions.csv").read_bytes() != table:  # ours (dataset.json says so), damaged
        _say(f"{out / 'conditions.csv'} was not this build's (edited or damaged): written again")
        write_atomic(out / "conditions.csv", table, part_suffix=part_suffix())

    mine = [s for s in plan.shards if s.index % part_n == part_i]
    todo = []
    for s in mine:  # a shard is done only when it is this plan's shard, whole
        if (out / s.file).exists() and (why := not_this_shard(out, s, plan, head)) is not None:
            _say(f"{out / s.file} is not this build's ({why}): built again")
            (out / s.file).unlink()
        if not (out / s.file).exists():
            todo.append(s)
    done_samples = sum(len(s.rows) for s in mine) - sum(len(s.rows) for s in todo)
    # absolute: a cluster's workers do not share this process's working directory
    stamp = dataset_stamp(head)  # each shard records which dataset it is
    tasks = [_task(plan, catalog, s, Path(settings.output), stamp) for s in todo]
    bar = Progress(sum(len(s.rows) for s in mine), "sample", progress, done=done_samples)
    t0 = time.perf_counter()
    try:
        if tasks:  # a finished part starts no cluster
            with runner.start(settings) as run:
                for _, n, _ in run(run_task, tasks):
                    bar.update(n)
    except KeyboardInterrupt:
        raise _interrupted(out, mine, part_i, part_n, settings) from None
    finally:
        close_simulators()
        bar.close()
    elapsed = time.perf_counter() - t0
    complete = all((out / s.file).exists() for s in plan.shards)
    if complete:  # the other parts' shards too, whole, before a manifest vouches for them
        bad = [(s, why) for s in plan.shards if s.index % part_n != part_i
               and (why := not_this_shard(out, s, plan, head)) is not None]
        if bad:
            s, why = bad[0]
            raise InputError(f"{out / s.file} is not this build's ({why}); delete it and run "
                             f"--shard {s.index % part_n}/{part_n} again"
                             + (f" ({len(bad)} such shards)" if len(bad) > 1 else ""))
        _remove_dead_parts(out / "shards")
        _remove_dead_parts(out)
        manifest = {"complete": True, "shards": [
            {"file": s.file, "sha256": sha256_file(out / s.file)} for s in plan.shards]}
        write_atomic(out / "manifest.json", json_bytes(manifest), part_suffix=part_suffix())
    return {"directory": str(out), "built_shards": len(tasks), "skipped_shards": len(mine) -
            len(tasks), "samples_built": sum(len(t.rows) for t in tasks),
            "seconds": round(elapsed, 3), "complete": complete}


def not_this_shard(out: Path, s: ShardPlan, plan: Plan, head: dict) -> str | None:
    """Why ``out / s.file`` is not shard ``s`` of ``plan`` (read whole: every member's CRC),
    whose header is ``head``, or None when it is: its samples and their conditions must be
    the plan's, exactly (a shard of another seed, config or dataset, copied in, is told
    apart), and it must be stamped as this dataset's (``foreign_shard``, the readers' check:
    a shard of the same plan built with another lidar, backend, sensor, ... is another
    dataset's; one written before shards were stamped is not what this build writes)."""
    try:
        shard = Shard.load(out / s.file)
    except InputError:
        return "unreadable, cut short or damaged"
    if not np.array_equal(shard.sample_id, s.rows) or \
            not np.array_equal(shard.conditions, plan.table[s.rows]):
        return "its samples or their conditions are another build's"
    if shard.dataset is None:
        return "written before shards recorded their dataset"
    if (why := foreign_shard(shard, head)) is not None:
        return f"another dataset's: {why}"
    return None


def _say(message: str, command: str = "apcg dataset build") -> None:
    """One line on stderr while a build goes on (what it found and did)."""
    import sys
    print(f"{command}: {message}", file=sys.stderr, flush=True)


def _interrupted(out: Path, mine: list[ShardPlan], part_i: int, part_n: int,
                 settings: RunSettings) -> BuildInterrupted:
    """After Ctrl-C, once the workers are stopped: drop the temporary files of this build's
    dead writers (a half-written shard never has its final name anyway) and say where the
    build stands. A cluster's shards still running finish on their own: theirs are left."""
    if settings.writers_are_local:
        _remove_dead_parts(out / "shards")
        _remove_dead_parts(out)
    done = sum((out / s.file).exists() for s in mine)
    of = f" of --shard {part_i}/{part_n}" if part_n > 1 else ""
    return BuildInterrupted(f"interrupted: {done} of {len(mine)} shards{of} are done in {out}; "
                            "run the same command again to resume (finished shards are kept)")


def _task(plan: Plan, catalog, s: ShardPlan, out: Path, dataset: str | None = None) \
        -> ShardTask:
    t = plan.types[s.type_code]
    table = plan.table[s.rows]
    return ShardTask(index=s.index, path=str(out / s.file), type_catalog_index=t.index,
                     depth_length_m=catalog.depth_length_m(t), rows=s.rows, table=table,
                     nu=plan.space.encode(table), backend=plan.config["backend"],
                     quantize=bool(plan.config.get("quantize", True)),
                     supersample=int(plan.config.get("supersample", 4 if plan.sensor else 1)),
                     fine_cloud_points=int(plan.config.get("fine_cloud_points", 10_000)),
                     lidar=plan.lidar.to_dict(),
                     sensor=plan.sensor.to_dict() if plan.sensor else None,
                     incidence=bool(plan.config.get("incidence", False)),
                     seed=int(plan.config.get("seed", 0)), dataset=dataset)


def dataset_info(directory, verify: bool = False, require_complete: bool = False) -> dict:
    """Summary of a dataset directory; ``verify`` checks the header against the config it
    records (the plan made again: counts, types, shards, condition space), conditions.csv
    against the same plan, and loads every shard, checking its hash and that it holds the
    samples the header and conditions.csv place in it; ``require_complete`` raises unless
    every shard and the manifest are there. A damaged manifest is named; a finished dataset
    (one with a manifest) missing a shard it lists is refused when verified."""
    out = Path(directory)
    head = read_header(out)
    shards = head["shards"]
    present = [s for s in shards if (out / s["file"]).exists()]
    has_manifest = (out / "manifest.json").exists()
    if has_manifest:
        read_manifest(out)  # a damaged one is named, whatever else is asked
    if require_complete and (len(present) < len(shards) or not has_manifest):
        raise InputError(f"dataset {out} is not complete: {len(present)} of {len(shards)} "
                         "shards present; run the same `apcg dataset build` again to finish it")
    complete = False
    if has_manifest:
        try:
            check_complete(out, head)
            complete = True
        except InputError:
            if verify or require_complete:
                raise
            if len(present) == len(shards):  # the manifest itself is wrong: name it
                raise
    info = {"directory": str(out), "name": head["name"], "format_version": head["format_version"],
            "backend": head["config"].get("backend"), "n_types": len(head["types"]),
            "n_samples": head["n_samples"], "n_train": head["n_train"], "n_test": head["n_test"],
            "shards_total": len(shards), "shards_present": len(present),
            "complete": complete,
            "sensor": head.get("sensor", {}).get("name", "ideal"),
            "incidence": bool(head["config"].get("incidence", False)),
            "bytes_on_disk": sum((out / s["file"]).stat().st_size for s in present)}
    n_done = sum(s["n_samples"] for s in present)
    info["samples_present"] = n_done
    if verify:
        from apcg_core.catalog.catalog import default_catalog
        cfg = dict(head["config"])
        if "sensor" in head:  # the sensor as recorded: its file need not exist any more
            cfg["sensor"] = dict(head["sensor"])
        plan = make_plan(cfg, default_catalog())
        _check_header(out, head, plan)
        sums = {m.get("file"): m.get("sha256") for m in read_manifest(out)["shards"]
                if isinstance(m, dict)}
        bad = []  # each "file (why)"
        if (out / "conditions.csv").exists() and (out / "conditions.csv").read_bytes() != \
                conditions_csv(plan):
            # a pure function of the config: made again, compared
            bad.append("conditions.csv (not this config's plan)")
        index = read_condition_index(out, head) if not bad else None
        n_points = clipped = clamped = empty = signal = 0
        for s in present:
            p = out / s["file"]
            try:
                sh = load_shard(out, s, index, head) if index is not None else Shard.load(p)
            except InputError as exc:  # unreadable, or another dataset's (which, named)
                bad.append(f"{s['file']} ({exc})")
                continue
            if sums.get(s["file"]) not in (None, sha256_file(p)):
                bad.append(f"{s['file']} (its bytes are not those manifest.json records)")
                continue
            if (sh.cos_incidence is None) == info["incidence"]:
                bad.append(f"{s['file']} (cos_incidence "
                           f"{'missing' if info['incidence'] else 'present'} where the "
                           "config says incidence = "
                           f"{'true' if info['incidence'] else 'false'})")
                continue
            n_points += len(sh.pixel)
            clipped += int(sh.clipped.sum())
            clamped += int(sh.n_clamped.sum())
            empty += int((np.diff(sh.offsets) == 0).sum())
            signal += int(sh.label.sum()) if sh.label is not None else 0
        if bad:
            raise InputError(f"damaged or foreign files in {out}: {'; '.join(bad)}; delete "
                             "them and run the same build again to remake them")
        info.update({"points": n_points, "mean_points_per_sample": n_points / max(n_done, 1),
                     "clipped_samples": clipped, "clamped_pixels": clamped,
                     "empty_samples": empty, "verified": True})
        if "sensor" in head:
            info.update({"signal_points": signal, "noise_points": n_points - signal})
    return info


def _check_header(out: Path, head: dict, plan: Plan) -> None:
    """dataset.json against the plan of the config it records: what it says of the samples,
    types and shards must be what that config makes (an edited header is named)."""
    expect = {"n_samples": plan.n_samples,
              "n_train": int((plan.split == "train").sum()),
              "n_test": int((plan.split == "test").sum()),
              "shards": [{"index": s.index, "file": s.file, "split": s.split,
                          "type_code": s.type_code, "n_samples": len(s.rows)}
                         for s in plan.shards],
              "types": [{"code": i, "name": t.name, "kind": t.kind, "range_band": t.range_band}
                        for i, t in enumerate(plan.types)],
              "condition_space": plan.space.to_dict(), "lidar": plan.lidar.to_dict(),
              "grid_values": plan.values}
    found = dict(head)
    found["types"] = [{k: t.get(k) for k in ("code", "name", "kind", "range_band")}
                      if isinstance(t, dict) else t for t in head.get("types", [])]
    differ = [k for k, v in expect.items()
              if json_bytes(found.get(k)) != json_bytes(v)]
    if differ:
        raise InputError(f"{out / 'dataset.json'} does not match the config it records: "
                         f"{', '.join(differ)} differ from what that config makes (the header "
                         "was edited, or is another build's); build the dataset again")
def time_engine_build(config, engine: str = "dask", workers: int = 2, out_dir=None,
                      shard_spec: str | None = None) -> dict:
    """Build ``config`` with ``engine`` and ``workers`` into ``out_dir`` (a fresh temporary
    directory when None) and time it, cluster start-up included: for benches.

    Returns ``seconds`` (wall, whole build), ``rays`` (rays cast in the built shards, 0 for
    the points backend), ``samples`` and ``shards`` built."""
    import tempfile

    with contextlib.ExitStack() as stack:
        if out_dir is None:
            out_dir = Path(stack.enter_context(tempfile.TemporaryDirectory())) / "ds"
        t0 = time.perf_counter()
        summary = build_dataset(config, out_dir, workers=workers, engine=engine,
                                shard_spec=shard_spec, progress=False)
        seconds = time.perf_counter() - t0
        rays = sum(int(np.sum(Shard.load(p).n_rays, dtype=np.int64))
                   for p in sorted((Path(out_dir) / "shards").glob("*.npz")))
    return {"engine": engine, "workers": workers, "seconds": round(seconds, 3), "rays": rays,
            "samples": summary["samples_built"], "shards": summary["built_shards"]}
