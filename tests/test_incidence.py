"""An APCG+ model's incidence output (training/families/plus_incidence.py, SPEC section 8): the
dataset records each return's cosine of incidence (checked against the mesh's own faces), the
incidence network learns it and is exported beside the model without touching the model's own
network, the photon stage reads it, and what cannot be trained or loaded is refused by name."""

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog import default_catalog
from apcg_core.depth import DEFAULT_LIDAR
from apcg_core.errors import InputError
from apcg_core.families import default_model_dir, load_model
from apcg_core.sensor import generated as G
from dataset_builder.build import build_dataset
from dataset_builder.rays import sample_frames
from training.data import DepthDataset

pytest.importorskip("torch")
trimesh = pytest.importorskip("trimesh")

BASE = default_model_dir()
SMALL = {"seed": 3, "backend": "embree", "shard_size": 50, "test_fraction": 0.2,
         "sampling": "random", "samples_per_type": 12,
         "types": ["A320neo", "F-16C Fighting Falcon", "Mavic 3", "UH-60 Black Hawk"]}


def slope_only(directory: Path, out: Path) -> Path:
    """A copy of the model in ``directory`` without its incidence network (its photons read
    the range's slope)."""
    shutil.copytree(directory, out)
    for f in out.glob("incidence*"):
        f.unlink()
    meta = json.loads((out / "model.json").read_text())
    (out / "model.json").write_text(json.dumps(
        {k: v for k, v in meta.items() if k not in ("incidence", "incidence_log")}))
    return out


def _build(tmp_path, name, **cfg) -> Path:
    out = tmp_path / name
    build_dataset({**SMALL, **cfg}, out, progress=False)
    return out


@pytest.fixture(scope="module")
def every_type(tmp_path_factory) -> Path:
    """Two conditions of every catalog type with their cosines: the default model's types."""
    out = tmp_path_factory.mktemp("incidence") / "ds"
    build_dataset({**SMALL, "types": "all", "samples_per_type": 2, "test_fraction": 0.5,
                   "shard_size": 1000, "incidence": True}, out, progress=False)
    return out


def test_incidence_adds_each_returns_cosine_and_changes_nothing_else(tmp_path):
    plain = _build(tmp_path, "plain", quantize=False)
    inc = _build(tmp_path, "inc", quantize=False, incidence=True)
    head = json.loads((inc / "dataset.json").read_text())
    cat = default_catalog()
    checked = 0
    for shard in head["shards"]:
        a, b = np.load(inc / shard["file"]), np.load(plain / shard["file"])
        assert set(a.files) == set(b.files) | {"cos_incidence"}
        for k in b.files:  # the standard cloud byte for byte
            if k != "dataset":  # which dataset each is (docs/DATASET.md): not the same one
                assert np.array_equal(a[k], b[k]), (shard["file"], k)
        cos = a["cos_incidence"].astype(np.float64)
        assert cos.dtype == np.float64 and len(cos) == len(a["pixel"])
        assert ((cos >= 0) & (cos <= 1)).all()
        # against the mesh itself: the face each cell's ray meets first (trimesh's own ray
        # query, in the body frame), its normal against the ray
        t = cat.get(head["types"][shard["type_code"]]["name"])
        mesh = cat.mesh(t)
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        table = a["conditions"]
        m, c = sample_frames(table)
        s = np.repeat(np.arange(len(table)), np.diff(a["offsets"]))
        row, col = np.divmod(a["pixel"].astype(np.int64), DEFAULT_LIDAR.width)
        w, h = DEFAULT_LIDAR.w_of_col(col), DEFAULT_LIDAR.h_of_row(row)
        alpha, beta = DEFAULT_LIDAR.cell_centre_angles(w, h, table[s, 2])
        d = np.stack([np.cos(beta) * np.sin(alpha), np.sin(beta),
                      np.cos(beta) * np.cos(alpha)], axis=1)
        origin = np.einsum("nj,njk->nk", -c[s], m[s])  # observation -> body: x (M^T)
        direction = np.einsum("nj,njk->nk", d, m[s])
        # start the rays near the target (float32 queries at kilometres lose the faces)
        r0 = table[s, 1] - 200.0
        face = tm.ray.intersects_first(origin + direction * r0[:, None], direction)
        met = face >= 0
        assert met.mean() > 0.97, (t.name, met.mean())
        want = np.abs((tm.face_normals[face[met]] * direction[met]).sum(axis=1))
        err = np.abs(cos[met] - want)
        assert np.median(err) < 2e-3 and (err < 0.02).mean() > 0.95, (t.name, err.max())
        checked += int(met.sum())
    assert checked > 500
    from dataset_builder.build import dataset_info
    assert dataset_info(inc, verify=True)["incidence"] is True
    assert dataset_info(plain, verify=True)["incidence"] is False
    assert DepthDataset(plain, "train").cos_incidence is None
    assert len(DepthDataset(inc, "train").cos_incidence) == len(DepthDataset(inc, "train").pixel)


def test_incidence_is_refused_where_it_cannot_be_recorded(tmp_path):
    with pytest.raises(InputError, match="incidence = true records .* a sensor's dataset"):
        _build(tmp_path, "a", incidence=True, sensor="1550nm-day")
    with pytest.raises(InputError, match="incidence = true needs a ray-casting backend"):
        _build(tmp_path, "b", incidence=True, backend="points")
    with pytest.raises(InputError, match="incidence.*true or false"):
        _build(tmp_path, "c", incidence="yes")
    for name in ("a", "b", "c"):
        assert not (tmp_path / name / "manifest.json").exists()


def _train(every_type, run, *extra, init=BASE) -> int:
    from apcg_core.cli import main
    return main(["train", "--data", str(every_type), "-o", str(run), "--family",
                 "apcg-plus-incidence", "--init", str(init), "--width", "0.75", "--sheet", "32",
                 "--head", "upconv", "--no-progress", *extra])


def _error(model, ds) -> float:
    """Mean |cosine - the data's| at every return of ``ds``'s training half."""
    table = ds.conditions.copy()
    codes = [model.types.names.index(ds.types.name(int(c))) for c in table[:, 0]]
    table[:, 0] = codes
    row, col = np.divmod(ds.pixel, ds.width)
    from apcg_core.cloud import PointCloud
    cloud = PointCloud(np.zeros((len(row), 3)), np.zeros(len(row)), ds.lidar.w_of_col(col),
                       ds.lidar.h_of_row(row), np.repeat(np.arange(len(ds)),
                                                         np.diff(ds.offsets)))
    return float(np.abs(model.incidence_of(table, cloud) - ds.cos_incidence).mean())


def test_the_incidence_output_learns_and_is_exported_beside_the_model(every_type, tmp_path,
                                                                      capsys):
    from training.export import export_model
    start = tmp_path / "start"
    assert _train(every_type, start, "--steps", "1", "--lr", "1e-12", "--no-bf16") == 0
    assert _train(every_type, tmp_path / "run", "--steps", "150", "--lr", "3e-3",
                  "--no-bf16") == 0
    assert json.loads((tmp_path / "run" / "train_config.json").read_text())["train"][
        "bf16"] is False
    ds = DepthDataset(every_type, "train")
    before = load_model(export_model(start, tmp_path / "m0"))
    out = export_model(tmp_path / "run", tmp_path / "m")
    after = load_model(out)
    e0, e1 = _error(before, ds), _error(after, ds)
    assert e0 > 0.15 and e1 < 0.8 * e0, (e0, e1)  # a cosine of one half everywhere, at first
    # the model itself, untouched: its network, threshold and its own run's record
    for name in ("sheets.onnx", "train_config.json", "log.csv", "tau_sweep.json"):
        assert (out / name).read_bytes() == (BASE / name).read_bytes(), name
    assert after.family == "apcg-plus" and after.tau == load_model(BASE).tau
    assert after.draws_incidence
    assert not load_model(slope_only(BASE, tmp_path / "slope")).draws_incidence
    rec = after.meta["incidence"]
    assert rec["net"]["outputs"] == 1 and rec["trained_steps"] == 150
    assert rec["train"]["init"] == str(BASE)
    assert (out / "incidence_log.csv").read_text().startswith("step,")
    assert json.loads((out / "incidence_train_config.json").read_text())["train"][
        "family"] == "apcg-plus-incidence"
    # the photon stage reads it: the same sub-rays as without it, their cosines the output's
    table = np.array([[0, 4200.0, np.radians(3.5), np.radians(2.0), 0.6, 0.02],
                      [0, 5100.0, np.radians(3.2), np.radians(3.0), -0.8, -0.05]])
    names = ["A320neo", "F-16C Fighting Falcon"]
    m = copy.copy(after)
    m.use_lidar(DEFAULT_LIDAR)
    got = G.sub_ray_hits(m, table, names, DEFAULT_LIDAR)
    slope = copy.copy(m)
    slope.draws_incidence = False
    ref = G.sub_ray_hits(slope, table, names, DEFAULT_LIDAR)
    assert len(got.cos) > 100
    for k in ("sample", "w", "h", "range_m"):
        assert np.array_equal(getattr(got, k), getattr(ref, k)), k
    assert not np.allclose(got.cos, ref.cos)
    fine = G.sub_ray_model(m, DEFAULT_LIDAR)
    conds = fine.conditions(names, table[:, 1:])
    cloud = fine.generate(conds).cloud
    want = fine.incidence_of(fine.repeated_conditions(conds, 1), cloud)
    hits = G.hits_of_cloud(cloud, table[:, 2], fine.lidar, len(table), want)
    inside = G.cells_of_fine_hits(hits, DEFAULT_LIDAR)
    assert np.array_equal(inside.cos, got.cos)
    # each cosine stays with its own point whatever order the cloud comes in
    order = np.random.default_rng(0).permutation(len(cloud))
    from apcg_core.cloud import PointCloud
    shuffled = PointCloud(cloud.xyz[order], cloud.range_m[order], cloud.cell_w[order],
                          cloud.cell_h[order], cloud.sample[order])
    again = G.hits_of_cloud(shuffled, table[:, 2], fine.lidar, len(table), want[order])
    assert np.array_equal(again.cos, hits.cos) and np.array_equal(again.w, hits.w)
    # the model the run started from is an input of its export: never its output, even with
    # --force, though the command line does not name it
    base_copy = slope_only(BASE, tmp_path / "base")
    assert _train(every_type, tmp_path / "from_copy", "--steps", "1", "--no-bf16",
                  init=base_copy) == 0
    before_bytes = {f.name: f.read_bytes() for f in base_copy.iterdir()}
    from apcg_core.cli import main
    assert main(["export", "--run", str(tmp_path / "from_copy"), "-o", str(base_copy),
                 "--force"]) == 2
    assert "is the model this run was trained from (its --init)" in capsys.readouterr().err
    assert {f.name: f.read_bytes() for f in base_copy.iterdir()} == before_bytes
    # a model written from this one without its incidence network says so, and loads
    from training.distill import DistillConfig, distill
    from training.families.apcg_plus import PLUS
    assert not PLUS.untrained(after, tmp_path / "u").draws_incidence
    student = distill(out, tmp_path / "d", DistillConfig(teacher=str(out), width=0.25,
                                                         head="upconv", steps=1, batch_size=4,
                                                         checkpoint_every=1000),
                      device="cpu", progress=False)
    assert not load_model(student["model"]).draws_incidence
    # trained again on a model that has one: the record is the new run's alone
    assert _train(every_type, tmp_path / "again", "--steps", "2", "--no-bf16", init=out) == 0
    again_model = load_model(export_model(tmp_path / "again", tmp_path / "m2", log_every=2))
    assert again_model.meta["incidence"]["trained_steps"] == 2
    assert again_model.meta["incidence_log"].startswith("incidence_log.csv keeps every 2nd")
    assert (tmp_path / "m2" / "sheets.onnx").read_bytes() == (BASE / "sheets.onnx").read_bytes()


def test_what_cannot_be_trained_or_loaded_is_refused(every_type, tmp_path, capsys):
    from apcg_core.cli import main
    assert main(["train", "--data", str(every_type), "-o", str(tmp_path / "a"), "--family",
                 "apcg-plus-incidence", "--width", "0.75", "--sheet", "32", "--head", "upconv",
                 "--steps", "1", "--no-progress"]) == 2
    assert "give the model with --init MODEL" in capsys.readouterr().err
    plain = _build(tmp_path, "plain", types="all", samples_per_type=1, test_fraction=0.0,
                   shard_size=1000)
    assert _train(plain, tmp_path / "b", "--steps", "1") == 2
    assert "holds no cos_incidence: build it with incidence = true" in capsys.readouterr().err
    assert _train(every_type, tmp_path / "c", "--steps", "1", "--width", "0.5") == 2
    assert "its network differs from the run's in width" in capsys.readouterr().err
    # a model directory whose incidence network and record disagree
    model = slope_only(BASE, tmp_path / "m")
    (model / "incidence.onnx").write_bytes((BASE / "sheets.onnx").read_bytes())
    with pytest.raises(InputError, match="incidence.onnx is there but model.json does not "
                                         "say what it is"):
        load_model(model)
    (model / "incidence.onnx").unlink()
    meta = json.loads((model / "model.json").read_text())
    (model / "model.json").write_text(json.dumps({**meta, "incidence": {"net": {}}}))
    with pytest.raises(InputError, match="incidence.onnx is missing"):
        load_model(model)
    with pytest.raises(InputError, match="has no incidence output"):
        load_model(slope_only(BASE, tmp_path / "s")).incidence_of(np.zeros((0, 6)), None)
    with pytest.raises(InputError, match="not a family of models"):
        from apcg_core.families import get_family
        get_family("apcg-plus-incidence").load(model)


def test_the_shipped_incidence_is_each_conditions_own_in_any_batch_and_order():
    """Over more conditions than one chunk, points in any order: each point's cosine is the
    one its condition gives alone (memory flat: the network runs a chunk at a time)."""
    from apcg_core.cloud import PointCloud
    from apcg_core.families.apcg_plus import CHUNK
    model = load_model()
    assert model.draws_incidence
    rng = np.random.default_rng(4)
    n = CHUNK + 37
    names = [["A320neo", "G550", "Mavic 3"][i % 3] for i in range(n)]
    far = np.array([name != "Mavic 3" for name in names])
    pose = np.column_stack([np.where(far, rng.uniform(3000, 9000, n), rng.uniform(100, 600, n)),
                            np.radians(rng.uniform(3, 4, n)), np.radians(rng.uniform(1, 5, n)),
                            np.radians(rng.uniform(-60, 60, n)),
                            np.radians(rng.uniform(-5, 5, n))])
    conds = model.conditions(names, pose)
    table = model.repeated_conditions(conds, 1)
    cloud = model.generate(conds).cloud
    order = rng.permutation(len(cloud))
    shuffled = PointCloud(cloud.xyz[order], cloud.range_m[order], cloud.cell_w[order],
                          cloud.cell_h[order], cloud.sample[order])
    got = model.incidence_of(table, shuffled)
    assert got.shape == (len(cloud),) and ((got > 0) & (got < 1)).all()
    for i in (0, 1, CHUNK - 1, CHUNK, n - 1):
        mine = shuffled.sample == i
        alone = PointCloud(shuffled.xyz[mine], shuffled.range_m[mine], shuffled.cell_w[mine],
                           shuffled.cell_h[mine], np.zeros(int(mine.sum()), np.int64))
        assert mine.any()
        assert np.array_equal(model.incidence_of(table[i:i + 1], alone), got[mine]), i


def test_blenders_ray_caster_records_the_same_cosines(tmp_path):
    """The `blender` backend (bpy in this process) names the faces its rays meet as embree
    does: the same returns, the same cosines."""
    pytest.importorskip("bpy")
    cfg = {"types": ["A320neo", "Mavic 3"], "samples_per_type": 4, "incidence": True}
    emb = _build(tmp_path, "e", **cfg)
    ble = _build(tmp_path, "b", backend="blender", **cfg)
    head = json.loads((emb / "dataset.json").read_text())
    n = 0
    for shard in head["shards"]:
        a, b = np.load(emb / shard["file"]), np.load(ble / shard["file"])
        assert np.array_equal(a["pixel"], b["pixel"]) and np.array_equal(a["offsets"],
                                                                          b["offsets"])
        assert np.abs(a["cos_incidence"].astype(float) - b["cos_incidence"]).max() < 0.01
        n += len(a["pixel"])
    assert n > 200
