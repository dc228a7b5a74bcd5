"""A dataset config's keys as they meet the build's other settings (probe p5, stop 55): a key
the build would ignore or contradict is refused in one line before anything is written, and a
refusal of an existing directory says what differs, no more. Real catalog, plans only (and one
tiny real build)."""

from __future__ import annotations

import pytest

from apcg_core.catalog.catalog import default_catalog
from apcg_core.errors import InputError
from dataset_builder.plan import load_config, make_plan
from tests.cli_run import one_error, run

BASE = """seed = 3
types = ["A320neo"]
sampling = "grid"
shard_size = 4
test_fraction = 0.25
[counts]
range_m = 1
elevation = 1
pitch = 1
yaw = 2
roll = 1
"""


def _plan(tmp_path, text, **over):
    path = tmp_path / "c.toml"
    path.write_text(text)
    return make_plan(load_config(str(path)), default_catalog(), **over)


def test_quantize_false_with_a_sensor_is_refused_as_no_quantize_is(tmp_path):
    """A sensor's points sit at their bins' centres: quantize = false was recorded in the
    header and silently not done (the arrays equal a quantized build's)."""
    with pytest.raises(InputError, match="quantize = false does not apply with a sensor"):
        _plan(tmp_path, 'quantize = false\nsensor = "1550nm-day"\n' + BASE)
    with pytest.raises(InputError, match="quantize = false does not apply with a sensor"):
        _plan(tmp_path, "quantize = false\n" + BASE, sensor="1550nm-night")  # --sensor
    assert _plan(tmp_path, "quantize = false\n" + BASE).n_samples == 2  # ideal: taken
    assert _plan(tmp_path, 'quantize = true\nsensor = "1550nm-day"\n' + BASE).n_samples == 2


def test_fine_cloud_points_is_taken_only_where_the_point_z_buffer_uses_it(tmp_path):
    text = "fine_cloud_points = 2000\n" + BASE
    with pytest.raises(InputError, match="fine_cloud_points is used by backend = \"points\""):
        _plan(tmp_path, text)  # embree, the default: it would be ignored
    with pytest.raises(InputError, match="blender"):
        _plan(tmp_path, 'backend = "points"\n' + text, backend="blender")  # --backend
    assert _plan(tmp_path, 'backend = "points"\n' + text).n_samples == 2


@pytest.mark.parametrize("pair", [[4, 3], [3, 3]])
def test_a_range_pair_is_refused_with_one_rule(tmp_path, pair):
    text = BASE.replace("[counts]", f"[ranges]\nelevation_deg = {pair}\n[counts]")
    with pytest.raises(InputError, match="lo < hi") as exc:
        _plan(tmp_path, text)
    assert "lo <= hi" not in str(exc.value)


def test_another_datasets_directory_is_refused_naming_only_what_differs(tmp_path, capsys):
    """The refusal listed the differing keys, then always added 'a type's mesh_sha256: its
    mesh changed in the catalog since', which read as one of them."""
    (tmp_path / "a.toml").write_text(BASE)
    (tmp_path / "b.toml").write_text(BASE.replace("seed = 3", "seed = 4"))
    out = tmp_path / "ds"
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "a.toml", "-o", out], capsys)
    assert rc == 0, err
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "b.toml", "-o", out], capsys)
    one_error(rc, err, "already holds a different dataset", "config")
    assert "mesh" not in err, err


def test_verify_says_why_a_shard_is_not_this_datasets(tmp_path, capsys):
    """A shard of the same plan built at another lidar, copied in: `dataset info --verify`
    said only 'corrupt files ... delete them'; it names the shard and the lidar."""
    import shutil
    (tmp_path / "a.toml").write_text(BASE)
    a, b = tmp_path / "a", tmp_path / "b"
    for out, extra in ((a, []), (b, ["--lidar", "double-cells"])):
        rc, _, err = run(["dataset", "build", "--config", tmp_path / "a.toml", "-o", out,
                          *extra], capsys)
        assert rc == 0, err
    shard = sorted((a / "shards").glob("*.npz"))[0]
    shutil.copyfile(b / "shards" / shard.name, shard)
    rc, _, err = run(["dataset", "info", a, "--verify"], capsys)
    one_error(rc, err, shard.name, "another lidar")
