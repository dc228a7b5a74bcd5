"""A dataset records the geometry it was cast against: a user type replaced by another mesh of
the same name and size (`apcg catalog add --force`) makes another dataset, whose shards are not
mixed into the first by a resumed build (probe finding, stop 54: a rebuilt shard of the new mesh
carried the old stamp and `dataset info --verify` said verified)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from apcg_core.catalog.catalog import mesh_digest
from apcg_core.io.dataset import Shard, dataset_stamp, foreign_shard
from tests.cli_run import one_error, run

# the user types these tests add stay out of the process's catalog (conftest.py)
pytestmark = pytest.mark.usefixtures("own_catalog")

CONFIG = """description = "mesh stamp"
seed = 3
backend = "embree"
shard_size = 4
test_fraction = 0.25
types = ["stamp box"]
sampling = "random"
samples_per_type = 8
"""


def _add(tmp_path, capsys, mesh, name):
    mesh.export(tmp_path / name)
    rc, _, err = run(["catalog", "add", tmp_path / name, "--name", "stamp box", "--force",
                      "--length-m", "20", "--kind", "aircraft"], capsys)
    assert rc == 0, err


@pytest.fixture
def closed_box():
    return trimesh.creation.box(extents=(20.0, 16.0, 4.0))


@pytest.fixture
def open_box(closed_box):
    # the same extents, one face gone: another surface, the same name, length and size
    return trimesh.Trimesh(closed_box.vertices, closed_box.faces[:-2], process=False)


def test_a_changed_mesh_is_another_dataset(tmp_path, capsys, closed_box, open_box):
    _add(tmp_path, capsys, closed_box, "a.obj")
    (tmp_path / "c.toml").write_text(CONFIG)
    out = tmp_path / "ds"
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "c.toml", "-o", out], capsys)
    assert rc == 0, err
    first = sorted((out / "shards").glob("*.npz"))
    assert len(first) >= 2
    import json
    head_a = json.loads((out / "dataset.json").read_text())
    assert len(head_a["types"][0]["mesh_sha256"]) == 64

    _add(tmp_path, capsys, open_box, "b.obj")
    first[0].unlink()  # a build stopped part way, resumed after the mesh changed
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "c.toml", "-o", out], capsys)
    one_error(rc, err, "already holds a different dataset", "'stamp box'", "mesh_sha256")
    assert not first[0].exists()  # nothing of the new mesh mixed in

    # a shard of the first mesh read under the second mesh's header is another dataset's
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "c.toml", "-o",
                      tmp_path / "ds2"], capsys)
    assert rc == 0, err
    head_b = json.loads((tmp_path / "ds2" / "dataset.json").read_text())
    assert head_b["types"][0]["mesh_sha256"] != head_a["types"][0]["mesh_sha256"]
    assert dataset_stamp(head_a) != dataset_stamp(head_b)
    shard_a = Shard.load(first[1])
    assert foreign_shard(shard_a, head_a) is None
    assert foreign_shard(shard_a, head_b) is not None


def test_a_header_without_mesh_digests_stamps_as_before():
    """Datasets built before headers recorded the mesh keep their stamps (their shards stay
    theirs): the type's part of the stamp is its catalog entry alone there."""
    head = {"config": {"seed": 1}, "lidar": {"width": 256}, "types": [
        {"name": "A320neo", "catalog_index": 0, "depth_length_m": 37.57}]}
    with_digest = {**head, "types": [{**head["types"][0], "mesh_sha256": "0" * 64}]}
    assert dataset_stamp(head) != dataset_stamp(with_digest)
    # records beside the catalog entry (kind, radius) never entered the stamp, and still not
    other = {**head, "types": [{**head["types"][0], "kind": "aircraft",
                                "bounding_radius_m": 20.0}]}
    assert dataset_stamp(other) == dataset_stamp(head)


def test_the_digest_is_the_geometry_bytes(closed_box, open_box):
    from apcg_core.catalog import Mesh
    a = Mesh(closed_box.vertices, closed_box.faces)
    b = Mesh(np.array(closed_box.vertices), np.array(closed_box.faces))
    assert mesh_digest(a) == mesh_digest(b)
    assert mesh_digest(a) != mesh_digest(Mesh(open_box.vertices, open_box.faces))
    moved = Mesh(closed_box.vertices + 1e-12, closed_box.faces)
    assert mesh_digest(moved) != mesh_digest(a)


def test_a_model_says_it_learned_a_user_type_from_a_mesh_replaced_since(tmp_path, capsys,
                                                                       closed_box, open_box):
    """A model's type table keeps a user type's mesh_sha256 (as the dataset it learned from
    recorded it); `generate` of that type warns once the catalog holds another mesh under
    the name (a taught model went on drawing the old shape without a word: stop 54)."""
    import json
    import shutil

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.families import default_model_dir, load_model
    _add(tmp_path, capsys, closed_box, "a.obj")
    cat = default_catalog()
    record = cat.mesh_record("stamp box")
    assert len(record["mesh_sha256"]) == 64 and cat.mesh_record("A320neo") == {}
    model = tmp_path / "m"  # the default, its A320neo row renamed the user's type, as teach does
    shutil.copytree(default_model_dir(), model)
    meta = json.loads((model / "model.json").read_text())
    row = next(r for r in meta["types"] if r["name"] == "A320neo")
    row.update(name="stamp box", catalog_index=cat.get("stamp box").index, **record)
    (model / "model.json").write_text(json.dumps(meta))
    assert load_model(model).types.records[row["code"]]["mesh_sha256"] == record["mesh_sha256"]
    gen = ["generate", "--model", model, "--type", "stamp box", "--range-m", "5000",
           "--elevation-deg", "3.5", "--pitch-deg", "2", "--force"]
    rc, _, err = run([*gen, "-o", tmp_path / "a.npz"], capsys)
    assert rc == 0 and "learned" not in err, err
    _add(tmp_path, capsys, open_box, "b.obj")
    rc, _, err = run([*gen, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 0, err
    warned = [ln for ln in err.splitlines() if "learned 'stamp box' from another mesh" in ln]
    assert len(warned) == 1 and "apcg teach" in warned[0], err


def test_a_type_records_mesh_digest_is_checked():
    from apcg_core.errors import InputError
    from apcg_core.typetable import TypeTable
    good = {"name": "x", "depth_length_m": 3.0, "mesh_sha256": "0" * 64}
    assert TypeTable.from_records([good]).records[0]["mesh_sha256"] == "0" * 64
    for bad in ("0" * 63, "G" * 64, 5, ["0" * 64]):
        with pytest.raises(InputError, match="mesh_sha256"):
            TypeTable.from_records([{**good, "mesh_sha256": bad}])
