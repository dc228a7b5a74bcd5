"""A large `apcg generate` as a resumable job: its clouds computed into part files beside the
output, then written into the output in order.

The dataset builder's way (dataset_builder/build.py: shards, resume, locks), for one output
file: a request of at least :data:`RESUMABLE_CLOUDS` clouds keeps its finished work in
``OUT.parts/``: ``job.json`` (what the request is: the output's header, the digests of the
model's files and of the conditions file), one ``part-NNNNNN.npz`` per :data:`PART_CLOUDS`
clouds (or per block, ``generation_cli.BLOCK_CLOUDS``, where a model's blocks are larger) (each
written whole through ``NAME.PID.part`` + fsync + rename, ``apcg_core.io.dataset.write_npz``,
each recording its job's digest and its place in it, :data:`JOB_KEY`: a part another job made
is made again, never written into this output), and the lock ``.generate.lock`` (one live
process per job, ``apcg_core.lock``). Ctrl-C (or SIGTERM) stops it with a line saying how far
it got; the same command then skips the parts present and continues. When every part is there
they are copied into the output in order (``CloudWriter``: memory flat in the number of clouds)
and the directory is removed. Every block is computed as the one-process path computes it (the
same blocks, seeds and sample offsets), so the output's bytes do not depend on where or in how
many runs its parts were made.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import zipfile
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .cloud import PHOTON_FIELDS, PointCloud
from .errors import InputError

# Requests of at least this many clouds run as a resumable job (smaller ones stream straight
# into the output: a Ctrl-C leaves nothing). 2^17 clouds take about 10-40 s here
# (bench/generate_profile.py), where losing the work to a Ctrl-C starts to cost; the part files
# cost one more write and read of the points (measured in docs/SCALE.md, "Generation").
RESUMABLE_CLOUDS = 2**17
# Clouds per part file: a part's clouds are held until it is written (~200 points, ~11 KB a
# cloud), so this bounds a job's memory. 2048 clouds (~23 MB) against 8192 on 10^5 clouds
# with --resumable: 14.7 s against 16.9 s, peak RSS 279 against 461 MB (docs/SCALE.md,
# "Generation at scale")
PART_CLOUDS = 2048
# The most clouds one request may ask for (rows x --count): a thousand times the paper's 10^6
# (its Fig. 18), about 7 TB of NPZ at the default model's ~150 points a cloud (48 bytes a
# point) and ~1.5 days of this 2-core machine; a job's plan (its blocks and parts) is held in
# memory, ~2 KB a block, and 10^11 clouds asked once filled 24 GB before the first cloud.
MAX_CLOUDS = 10**9
ENGINES_GROUP = "apcg.engines"  # entry points: name -> run_tasks(...) context (the builder's)
_FIELDS = ("xyz", "range_m", "cell_w", "cell_h", "sample")
# Each part also holds this member (last, after the clouds and counts): a short JSON string
# naming the job that made it (the digest of its job.json record) and which part of it it is
# (its number and sub-block range), so that a part copied from another job, or from another
# part, is made again instead of going into the output (:func:`_part_problem`).
JOB_KEY = "job"


def clouds_with_points(sample) -> int:
    """How many distinct clouds the points of one block belong to (``sample``: their cloud
    numbers, a block's short span). A count, not a sort: np.unique over every point of a
    100,000-cloud request took 0.9 s of the writing thread."""
    s = np.asarray(sample, np.int64)
    return int(np.count_nonzero(np.bincount(s - s.min()))) if s.size else 0


def block_seed(seed: int, block: int) -> int:
    """Block 0 keeps the seed (a one-block request is unchanged); later blocks get seeds
    drawn from (seed, block), so no two blocks of any two seeds share their noise."""
    if block == 0:
        return seed
    return int(np.random.SeedSequence([seed, block]).generate_state(1)[0])


def generate_block(model, sensor, seed: int, block: int, part, count: int, offset: int):
    """One block of a request (``generation_cli.blocks``' ``block``-th: ``part``'s rows
    ``count`` times, its clouds numbered from ``offset``): (stacked cloud, clouds). Noise
    from ``block_seed(seed, block)``, photons from (seed, cloud number): the same clouds
    wherever and whenever the block is made."""
    res = model.generate(part, count=count, seed=block_seed(seed, block))
    cloud = res.cloud
    if sensor is not None:
        from .sensor.generated import photon_generated
        cloud = photon_generated(cloud, res.table, res.conditions.names, model.lidar,
                                 sensor, seed, offset, model=model)
    cloud.sample = np.asarray(cloud.sample, np.int64) + offset
    return cloud, len(res.table)


@dataclass(frozen=True)
class PartTask:
    """One part file's work for an engine's worker (picklable): its blocks, and how to open
    the model as the command did (directory, runtime, tau, lidar) and the sensor."""

    index: int
    path: str
    blocks: list  # (block number, Conditions, count, first cloud number)
    model_dir: str
    runtime: str
    tau: float | None
    lidar: object  # the LidarParams --lidar pointed the model at, or None
    seed: int
    sensor: object  # SensorParams, or None: the ideal lidar
    photon_fields: tuple
    job: str | None = None  # what the part records of its job (:func:`part_stamp`)


_MODELS: dict = {}  # a worker's models, opened once per process


def _worker_model(task: PartTask):
    key = (task.model_dir, task.runtime, task.tau, task.lidar)
    if key not in _MODELS:
        from .families import load_model
        model = load_model(task.model_dir, runtime=task.runtime)
        if task.tau is not None:
            model.tau = model.check_tau(task.tau)
        if task.lidar is not None:
            model.use_lidar(task.lidar)
        if hasattr(model, "workers"):
            model.workers = 1  # a worker is one core: the engine runs one per core
        _MODELS.clear()
        _MODELS[key] = model
    return _MODELS[key]


def run_part(task: PartTask) -> tuple[int, int]:
    """An engine's task: compute a part's blocks and write its file whole. (part, clouds)."""
    model = _worker_model(task)
    model.expect_clouds(sum(len(part) * count for _, part, count, _ in task.blocks))
    held = [generate_block(model, task.sensor, task.seed, b, part, count, offset)
            for b, part, count, offset in task.blocks]
    _write_part(Path(task.path), held, task.photon_fields, f".{os.getpid()}.part", task.job)
    return task.index, sum(n for _, n in held)


class GenerateInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a resumable generate; the message says how far it got."""


def engine(name: str, workers: int, address: str | None, output: Path):
    """The engine ``name`` (``--engine``) as a context manager yielding ``run(fn, tasks)``:
    the dataset builder's engines (dataset_builder/tasks.py), found through the
    ``apcg.engines`` entry point, so the core imports nothing above it."""
    from importlib.metadata import entry_points
    found = {ep.name: ep for ep in entry_points(group=ENGINES_GROUP)}
    if "run_tasks" not in found:
        raise InputError(f"--engine {name} needs the dataset builder's engines (the apcg "
                         "package installed with pip, its sim and engine extras)")
    return found["run_tasks"].load()(name, workers=workers, address=address,
                                      output=str(output.resolve()))


def parts_dir(output) -> Path:
    return Path(str(output) + ".parts")


def job_record(meta: dict, model_dir, conditions) -> dict:
    """What makes two requests the same job: the output's header (model, family, runtime,
    seed, count, tau, lidar, sensor, conditions), the bytes of the model's files and of the
    conditions file."""
    from . import __version__
    from .io.dataset import sha256_file
    model_dir = Path(model_dir)
    files = {p.name: sha256_file(p) for p in sorted(model_dir.iterdir())
             if p.is_file() and p.suffix in (".json", ".onnx", ".pt", ".npz")
             and p.name not in ("evaluation.json", "tau_sweep.json")}
    return {"apcg": __version__, "header": meta, "model_files": files,
            "conditions_sha256": sha256_file(conditions) if conditions else None}


def job_digest(record: dict) -> str:
    """The digest of a job's record (job.json's bytes): what each of its parts records."""
    from .io.dataset import json_bytes
    return hashlib.sha256(json_bytes(record)).hexdigest()


def part_stamp(digest: str, i: int, per_part: int, n_subs: int) -> str:
    """What part ``i`` of the job ``digest`` records of itself (member ``JOB_KEY``): the job,
    the part's number and its range of sub-blocks (hence of the job's rows)."""
    return json.dumps({"job": digest, "part": i,
                       "blocks": [i * per_part, min((i + 1) * per_part, n_subs)]},
                      sort_keys=True, separators=(",", ":"))


def run_job(output, meta: dict, record: dict, photon_fields, subs, per_part: int, compute,
            lanes: int, progress_from, engine=None, task_of=None) -> tuple[int, int]:
    """Generate the sub-blocks ``subs`` (``compute(item)`` -> (cloud, clouds), in order,
    ``lanes`` at once) into part files of ``per_part`` sub-blocks each, skipping the parts
    present, then write the output from them; ``progress_from(clouds done)`` starts the
    progress bar once the job is known to be this one. With ``engine`` (a context manager
    yielding ``run(fn, tasks)``: the dataset builder's engines, through the ``apcg.engines``
    entry point) the missing parts are computed by its workers (``task_of(part, its blocks,
    path)`` -> :class:`PartTask`, :func:`run_part`) instead of in this process. Returns
    (points, empty clouds)."""
    from .io.dataset import json_bytes, write_atomic
    from .lock import ProcessLock
    from .testpoints import wait_point
    subs = list(subs)
    n_parts = -(-len(subs) // per_part)
    parts = parts_dir(output)
    if parts.exists() and not parts.is_dir():  # the user's file: kept, and named
        raise InputError(f"{parts} is a file, but this request keeps its finished parts in a "
                         f"directory of that name ({output}'s parts, so that it can resume); "
                         "move that file away, or choose another output name")
    suffix = f".{os.getpid()}.part"
    # The engine is checked (its name, its options, a cluster's address) and started before
    # the parts directory is made: a refused request leaves nothing behind.
    with (engine if engine is not None else nullcontext()) as run_tasks, \
            ProcessLock(parts / ".generate.lock", f"generate into {output}"):
        job = parts / "job.json"
        if job.exists():
            if _job_of(job) != json.loads(json_bytes(record)):
                raise InputError(f"{parts} holds the parts of another request (its job.json "
                                 "differs: model, conditions, options or apcg version); run "
                                 "the command that made them, or delete that directory")
        else:
            # job.json is written before any part: parts without it are of no known request
            # (copied, or its job.json deleted), never to be taken into this output
            if stray := sorted(parts.glob("part-*.npz")):
                raise InputError(f"{parts} holds {len(stray)} part file(s) ({stray[0].name}"
                                 f"{', ...' if len(stray) > 1 else ''}) but no job.json, so "
                                 "nothing says which request made them; delete that "
                                 "directory and run the command again")
            write_atomic(job, json_bytes(record), part_suffix=suffix)
        digest = job_digest(record)
        stamps = [part_stamp(digest, i, per_part, len(subs)) for i in range(n_parts)]
        done = {i for i in range(n_parts) if (parts / _part_name(i)).exists()}
        before = 0
        for i in sorted(done):
            path = parts / _part_name(i)
            if (why := _part_problem(path, stamps[i])) is not None:
                # a part job.json never made (copied in from another job or part): made again
                print(f"apcg generate: {path} is not this job's ({why}): made again",
                      file=sys.stderr, flush=True)
                path.unlink()
                done.discard(i)
                continue
            with _reading(path), np.load(path) as z:
                before += int(z["clouds"])
        progress = progress_from(before)
        todo = ((k, item) for k, item in enumerate(subs) if k // per_part not in done)

        def run(k_item):
            return (k_item[0], *compute(k_item[1]))
        try:
            if engine is not None:
                tasks = [replace(task_of(i, subs[i * per_part:(i + 1) * per_part],
                                         str((parts / _part_name(i)).resolve())),
                                 job=stamps[i])
                         for i in range(n_parts) if i not in done]
                for _, n in run_tasks(run_part, tasks):
                    progress.update(n)
                    wait_point("generate.part-written")
            else:
                held: list = []
                for k, cloud, n in in_order(run, todo, lanes):
                    held.append((cloud, n))
                    progress.update(n)
                    if k % per_part == per_part - 1 or k == len(subs) - 1:
                        _write_part(parts / _part_name(k // per_part), held, photon_fields,
                                    suffix, stamps[k // per_part])
                        held = []
                        wait_point("generate.part-written")
            points, empty = _write_output(output, meta, photon_fields, parts, n_parts,
                                          stamps)
        except KeyboardInterrupt:
            raise GenerateInterrupted(_how_far(parts, n_parts)) from None
        finally:
            progress.close()
        for i in range(n_parts):
            (parts / _part_name(i)).unlink()
        job.unlink()
    _remove_empty(parts)
    return points, empty


def in_order(fn, items, lanes: int = 1):
    """``fn(item)`` for each of ``items``, in order, computed in ``lanes`` threads (the
    model's own: its ``lanes``) while the caller writes what came before; at most
    ``2 * lanes + 1`` results wait, so memory stays bounded. On an exception or Ctrl-C in the
    caller, blocks not started are dropped and those running finish (a block is short)."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor
    pool = ThreadPoolExecutor(max(1, lanes), thread_name_prefix="apcg-generate")
    pending: deque = deque()
    try:
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > 2 * lanes:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _write_part(path: Path, held: list, photon_fields, suffix: str,
                stamp: str | None = None) -> None:
    """A part file of the clouds ``held`` ((cloud, clouds) per block), written field by
    field: beside the blocks, memory holds one concatenated field at a time; ``stamp``
    (:func:`part_stamp`: its job and place in it) recorded last."""
    from .io.dataset import write_npz
    clouds = [c for c, _ in held]

    def field(k):
        return lambda: np.concatenate([getattr(c, k) for c in clouds])
    members = [(k, field(k)) for k in (*_FIELDS, *photon_fields)]
    members.append(("clouds", np.int64(sum(n for _, n in held))))
    members.append(("empty", np.int64(sum(n - clouds_with_points(c.sample) for c, n in held))))
    if stamp is not None:
        members.append((JOB_KEY, np.array(stamp)))
    write_npz(path, members, part_suffix=suffix)


def _part_problem(path: Path, stamp: str) -> str | None:
    """Why the part file ``path`` is not the part whose :func:`part_stamp` is ``stamp``
    (another job's, another part's of this job, or one that records no job), or None. A
    damaged file is named by :func:`_reading` (InputError)."""
    with _reading(path), np.load(path) as z:
        rec = z[JOB_KEY] if JOB_KEY in z.files else None
        if rec is not None and (rec.ndim != 0 or rec.dtype.kind != "U"):
            return f"its {JOB_KEY} record is not a string"
        rec = str(rec) if rec is not None else None
    if rec is None:
        return "it records no job: written by another job or an older apcg"
    if rec == stamp:
        return None
    try:
        got = json.loads(rec)
    except json.JSONDecodeError:
        got = None
    want = json.loads(stamp)
    if not isinstance(got, dict):
        return f"its {JOB_KEY} record is damaged"
    if got.get("job") != want["job"]:
        return "it belongs to another job (another request's model, conditions or options)"
    return (f"it is part {got.get('part')} of this job (sub-blocks {got.get('blocks')}), not "
            f"part {want['part']} (sub-blocks {want['blocks']})")


def _write_output(output, meta, photon_fields, parts: Path, n_parts: int,
                  stamps: list | None = None) -> tuple[int, int]:
    """The parts, in order, into the output. Each part is checked whole first (that it is
    this job's part ``i``, ``stamps[i]``: :func:`_part_problem`; its zip, its members' types
    and lengths, every member's CRC: :func:`_part_ranges`); a foreign or damaged one is
    named, with what to do. Into an NPZ the checked bytes are copied by the kernel
    (``CloudWriter.write_ranges``: the same file as writing the arrays, without loading
    them); into other formats the arrays are loaded and written."""
    from .io.clouds import CloudWriter
    points = empty = 0
    with CloudWriter(output, meta, photon_fields=photon_fields) as out:
        for i in range(n_parts):
            path = parts / _part_name(i)
            if stamps is not None and (why := _part_problem(path, stamps[i])) is not None:
                raise InputError(f"{path} is not this job's ({why}); delete it and run the "
                                 "same command again: that part is computed again")
            if out.ext == ".npz":
                with _reading(path), open(path, "rb") as src:
                    ranges, n, part_empty = _part_ranges(src, out.fields)
                    out.write_ranges(src.fileno(), ranges, n)
                points += n
                empty += part_empty
                continue
            with _reading(path), np.load(path) as z:
                cloud = PointCloud(*(z[k] for k in _FIELDS),
                                   **{k: z[k] for k in photon_fields if k in PHOTON_FIELDS})
                empty += int(z["empty"])
            out.write(cloud)
            points += len(cloud)
    return points, empty


# what reading a damaged part file raises (zipfile.BadZipFile is a plain Exception)
_UNREADABLE = (ValueError, KeyError, OSError, EOFError, zipfile.BadZipFile)


def _job_of(job: Path) -> dict:
    """A parts directory's job.json, read; a damaged one is named, with what to do."""
    try:
        out = json.loads(job.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        out = exc
    if not isinstance(out, dict):
        why = f"not JSON: {out}" if isinstance(out, Exception) else "not a JSON object"
        raise InputError(f"{job} is damaged ({why}); delete {job.parent} and run the command "
                         "again (its parts cannot be matched to a request without it)")
    return out


@contextmanager
def _reading(path: Path):
    """Around every read of a part file: what a damaged one raises becomes one InputError
    naming it, with what to do."""
    try:
        yield
    except _UNREADABLE as why:
        if isinstance(why, zipfile.BadZipFile):
            why = f"not a readable zip: {why}"
        raise InputError(f"{path} is damaged ({why}); delete it and run the same command "
                         "again: that part is computed again, the others are kept") from None


def _part_ranges(src, fields: dict) -> tuple[dict, int, int]:
    """(field -> (offset, bytes, CRC-32 of the array's bytes), points, empty clouds) of the
    open part file ``src``, for the output's ``fields`` (name -> (dtype, row shape):
    ``CloudWriter.fields``), every member read once to check its CRC against the zip's. A part
    that is not what :func:`_write_part` writes raises ValueError (:func:`_reading` names it)."""
    from .io.crc import crc32, crc32_combine
    fmt = np.lib.format
    with zipfile.ZipFile(src) as z:
        infos = {i.filename: i for i in z.infolist()}
        empty = int(np.load(z.open("empty.npy")))
    ranges, n = {}, None
    for k, (want, row) in fields.items():
        info = infos.get(f"{k}.npy")
        if info is None or info.compress_type != zipfile.ZIP_STORED:
            raise ValueError(f"no stored member {k}.npy")
        local = os.pread(src.fileno(), 30, info.header_offset)
        if len(local) < 30 or local[:4] != b"PK\x03\x04":
            raise ValueError(f"{k}.npy: no local header where the zip says")
        start = (info.header_offset + 30 + int.from_bytes(local[26:28], "little")
                 + int.from_bytes(local[28:30], "little"))
        src.seek(start)
        version = fmt.read_magic(src)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"{k}.npy: .npy format {version}")
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(src)
        head = src.tell() - start
        if dtype != want or fortran or tuple(shape[1:]) != row or \
                (n is not None and shape[0] != n):
            raise ValueError(f"{k}.npy holds {dtype}{shape}, not {want}"
                             f"{('N', *row)} of {n if n is not None else 'N'} points")
        n = shape[0]
        count = info.file_size - head
        if count != n * want.itemsize * int(np.prod(row, dtype=np.int64)):
            raise ValueError(f"{k}.npy has {count} bytes for {shape}")
        crc, done = 0, 0
        while done < count:
            data = os.pread(src.fileno(), min(1 << 24, count - done), start + head + done)
            if not data:
                raise ValueError(f"{k}.npy ends {count - done} bytes early")
            crc = crc32(data, crc)
            done += len(data)
        src.seek(start)
        if crc32_combine(crc32(src.read(head)), crc, count) != info.CRC:
            raise ValueError(f"{k}.npy: its bytes do not match its CRC")
        ranges[k] = (start + head, count, crc)
    return ranges, int(n or 0), empty


def _remove_empty(parts: Path) -> None:
    try:
        for p in parts.glob("*.part"):  # a dead writer's temporary file (none normally)
            p.unlink()
        parts.rmdir()
    except OSError:
        pass  # something else lives there: left as it is


def _part_name(i: int) -> str:
    return f"part-{i:06d}.npz"


def _how_far(parts: Path, n_parts: int) -> str:
    done = sum((parts / _part_name(i)).exists() for i in range(n_parts))
    return (f"interrupted: {done} of {n_parts} parts are done in {parts}; run the same command "
            "again to resume (finished parts are kept)")
