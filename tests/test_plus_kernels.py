"""The APCG+ reader's compiled loops (apcg_core/families/plus_kernels.py) against the numpy
reader they replace (PlusModel.clouds_of): the same clouds, byte for byte, on the shipped
model's sheets at a few hundred random conditions of its condition space (aircraft and
drones, the nearest and the farthest ranges), at every lidar preset (half and double cells,
anisotropic cells, other bins), on speckled and float64 sheets, without quantising, with
nothing above tau, and for no condition and one; under every draw (plus_draw.py)."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

pytest.importorskip("numba")
pytest.importorskip("onnxruntime")

from fresh_process import printed  # noqa: E402

from apcg_core.families import load_model, plus_kernels  # noqa: E402
from apcg_core.families.apcg_plus import CHUNK  # noqa: E402
from apcg_core.families.plus_draw import DRAWS  # noqa: E402
from apcg_core.lidar import lidar_preset_names, load_lidar  # noqa: E402
from apcg_core.typetable import Conditions  # noqa: E402

FIELDS = ("xyz", "range_m", "cell_w", "cell_h", "sample")


@pytest.fixture(scope="module")
def model():
    return load_model(None)


@pytest.fixture(scope="module")
def drawn(model):
    """300 random conditions over the model's space (a third of them drones, whose ranges
    are the near band), the first rows at the nearest and the farthest ranges, and their
    sheets."""
    rng = np.random.default_rng(11)
    n = 300
    nu = rng.uniform(-1, 1, (n, 6))
    table = model.space.decode(nu)
    drones = np.asarray(model.space.drone_types)
    table[: n // 3, 0] = rng.choice(drones, n // 3)
    lo, hi = model.space.bounds(table)
    table[:, 1] = rng.uniform(lo[:, 1], hi[:, 1])
    table[:8, 1] = lo[:8, 1]  # the nearest: boxes larger than the window
    table[8:20, 1] = hi[8:20, 1]  # the farthest: a few cells a cloud
    table[n // 3:n // 3 + 10, 1] = hi[n // 3:n // 3 + 10, 1]  # far aircraft
    table = model.space.check(table)
    assert model.space.is_drone(table[:, 0]).sum() >= n // 3
    return table, model.sheets(table)


def _same(a, b, what):
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, (what, f, x.dtype, y.dtype)
        assert np.array_equal(x, y) and x.tobytes() == y.tobytes(), (what, f)


def _both(model, table, sheets, what):
    """Both readers, under every draw (plus_draw.DRAWS): the same bytes; returns the
    model's own draw's cloud."""
    own = model.draw
    try:
        for draw in DRAWS.values():
            model.draw = draw
            want = model.clouds_of(table, sheets, compiled=False)
            got = model.clouds_of(table, sheets, compiled=True)
            _same(got, want, (what, draw.name))
            if draw == own:
                mine = want
    finally:
        model.draw = own
    return mine


def test_the_kernels_are_there():
    # CI installs the sim extra, numba included: the comparisons below must not be numpy
    # against numpy.
    os.environ.pop(plus_kernels.ENV, None)
    assert plus_kernels.enabled()
    plus_kernels.require()
    assert plus_kernels.loaded() and plus_kernels.use_for(1)


@pytest.mark.parametrize("preset", sorted(lidar_preset_names()))
def test_compiled_reader_gives_the_numpy_bytes_at_every_lidar(model, drawn, preset):
    table, sheets = drawn
    lidar = load_lidar(preset)
    keep = model.lidar
    model.use_lidar(lidar)
    try:
        want = _both(model, table, sheets, preset)
        # the chunks generate reads, each on its own
        for s in range(0, len(table), CHUNK // 2):
            _both(model, table[s:s + CHUNK // 2], sheets[s:s + CHUNK // 2], (preset, s))
    finally:
        model.use_lidar(keep)
    counts = np.bincount(want.sample, minlength=len(table))
    drone = model.space.is_drone(table[:, 0])
    assert len(want.range_m) > 5000, preset
    assert (counts[drone] > 0).sum() > 50 and (counts[~drone] > 0).sum() > 50, preset
    assert (counts[8:20] > 0).any(), preset  # the farthest give points too


@pytest.mark.parametrize("kind", ["speckled", "noise", "float64"])
def test_compiled_reader_on_other_sheets(model, drawn, kind):
    """Many separate blobs a row and reads at the sheet's border (speckled), rows live almost
    everywhere (noise: sheet values about tau), and float64 sheets (no widening)."""
    table, sheets = drawn
    rng = np.random.default_rng(5)
    if kind == "speckled":
        sheets = np.where(rng.random(sheets.shape) < 0.03, 5.0, -5.0).astype(np.float32)
    elif kind == "noise":
        sheets = rng.normal(model.tau, 1.0, sheets.shape).astype(np.float32)
    else:
        sheets = sheets.astype(np.float64) + rng.normal(0, 1e-3, sheets.shape)
    for preset in ("paper", "anisotropic"):
        keep = model.lidar
        model.use_lidar(load_lidar(preset))
        try:
            want = _both(model, table, sheets, (kind, preset))
        finally:
            model.use_lidar(keep)
        assert len(want.range_m) > 1000, (kind, preset)


def test_other_thresholds_and_unquantised_ranges(model, drawn):
    table, sheets = drawn
    tau, quantize = model.tau, model.quantize
    try:
        for t in (*model.TAUS, 0.25):
            model.tau = t
            for q in (True, False):
                model.quantize = q
                _both(model, table[:100], sheets[:100], (t, q))
    finally:
        model.tau, model.quantize = tau, quantize


def test_nothing_above_tau_no_condition_and_one(model, drawn):
    table, sheets = drawn
    tau = model.tau
    try:
        model.tau = 1e9  # no sheet value is above it: every cloud empty
        empty = _both(model, table, sheets, "tau 1e9")
        assert len(empty.range_m) == 0 and empty.xyz.shape == (0, 3)
    finally:
        model.tau = tau
    none = model.sheets(table[:0])  # what generate gets for no condition: (0, 2, 1, 1)
    for t, sh in ((table[:0], none), (table[:0], sheets[:0])):
        got = _both(model, t, sh, "no condition")
        assert len(got.range_m) == 0
    for i in (0, 8, 150):
        got = _both(model, table[i:i + 1], sheets[i:i + 1], ("one", i))
        assert len(got.range_m) > 0 and (got.sample == 0).all()


def test_generate_takes_the_kernels_by_the_environment(model, drawn, monkeypatch):
    """`APCG_KERNELS`: numpy never takes the compiled path, compiled does from the first call,
    and generate's clouds (chunks read side by side in threads) are the same bytes."""
    table, _ = drawn
    conditions = Conditions(model.types, np.repeat(table[:150], 4, axis=0))
    workers = model.workers
    model.workers = 2
    try:
        clouds = {}
        for mode in ("numpy", "compiled"):
            monkeypatch.setenv(plus_kernels.ENV, mode)
            assert plus_kernels.use_for(1) == (mode == "compiled")
            clouds[mode] = model.generate(conditions).cloud
    finally:
        model.workers = workers
    _same(clouds["compiled"], clouds["numpy"], "generate")
    assert len(clouds["numpy"].range_m) > 10_000


def test_the_kernels_hold_no_fused_multiply_add(model, drawn):
    # An FMA rounds once where the numpy code rounds twice: the kernels must not hold one.
    # Compile them again with their own options but without the cache, for the argument
    # types they were called with, and read the machine code.
    from numba import njit
    table, sheets = drawn
    model.clouds_of(table[:20], sheets[:20], compiled=True)
    model.clouds_of(table[:20], sheets[:20].astype(np.float64), compiled=True)
    k = plus_kernels.require()
    fused = re.compile(r"\b(v?fn?m(add|sub)\w*|fml[as]\w*)\b", re.IGNORECASE)
    for name in ("row_spans", "read_rows"):
        f = getattr(k, name)
        assert f.signatures, name
        options = {o: v for o, v in f.targetoptions.items() if o != "nopython"}
        again = njit(**options)(f.py_func)
        for sig in f.signatures:
            again.compile(sig)
        asm = "\n".join(again.inspect_asm().values())
        assert not fused.search(asm), (name, fused.search(asm).group(0))
        assert re.search(r"\b(v?mul[sp][sd]|fmul)\b", asm), name  # the pattern reads it


def test_the_loading_thread_makes_the_readers_first_call_with_a_blocks_types():
    """expect_clouds loads the compiled reader on a thread and calls it there on a probe with
    the argument types of a real block (numba loads each function from its cache at its first
    call in a process): a block read afterwards adds no compiled version of either kernel."""
    code = ("import time\n"
            "import numpy as np\n"
            "from apcg_core.families import load_model, plus_kernels\n"
            "from apcg_core.condition import DEG\n"
            "m = load_model(None)\n"
            "m.expect_clouds(plus_kernels.SWITCH_CLOUDS)\n"
            "t = time.time()\n"
            "while not plus_kernels.loaded() and time.time() - t < 300:\n"
            "    time.sleep(0.01)\n"
            "k = plus_kernels.require()\n"
            "before = [len(k.row_spans.overloads), len(k.read_rows.overloads)]\n"
            "c = m.conditions(['A320neo', 'Mavic 3'], [[6000.0, 3.5 * DEG, 0.02, 0.3, 0.01],\n"
            "                                      [300.0, 3.2 * DEG, 0.05, -0.4, 0.0]])\n"
            "table = m.repeated_conditions(c, 1)\n"
            "cloud = m.clouds_of(table, m.sheets(table), compiled=True)\n"
            "print(before, [len(k.row_spans.overloads), len(k.read_rows.overloads)], "
            "len(cloud) > 0)\n")
    out = printed(code, APCG_KERNELS="").split("]")
    assert out[0].strip() == "[1, 1" and out[1].strip() == "[1, 1", out
