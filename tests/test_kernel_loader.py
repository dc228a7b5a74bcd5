"""The core's compiled kernels load through one mechanism (apcg_core/kernel_loader.py): a fresh
process stays on numpy until it has put its set's switch of work through it (rent, then buy),
unless APCG_KERNELS says otherwise, and the package imports without numba."""

import pytest
from fresh_process import printed

SETS = {  # kernel module -> (its switch, the package that must import without numba)
    "apcg_core.sensor.kernels": ("SWITCH_HITS", "apcg_core.sensor"),
    "apcg_core.families.plus_kernels": ("SWITCH_CLOUDS", "apcg_core.families.apcg_plus"),
    "dataset_builder.kernels": ("SWITCH_RAYS", "dataset_builder.rays"),
}


@pytest.mark.parametrize("module", sorted(SETS))
@pytest.mark.parametrize("mode", ["", "numpy", "compiled"])
def test_a_process_loads_the_kernels_once_it_has_work_for_them(module, mode):
    switch, package = SETS[module]
    code = ("import importlib, sys\n"
            f"k = importlib.import_module({module!r})\n"
            f"importlib.import_module({package!r})\n"
            "print('numba' in sys.modules)\n"
            f"n = k.{switch}\n"
            "print(k.enabled(), k.loaded(), k.use_for(n // 2), k.use_for(0), k.loaded(),\n"
            "      k.use_for(n // 2), k.loaded(), k.use_for(1))\n")
    out = printed(code, APCG_KERNELS=mode).split()
    want = {"": "False True False False False False True True True",
            "numpy": "False False False False False False False False False",
            "compiled": "False True False True True True True True True"}[mode]
    assert out == want.split()


@pytest.mark.parametrize("module", sorted(SETS))
@pytest.mark.parametrize("mode", ["", "numpy"])
def test_work_said_to_be_coming_loads_the_kernels_beside_it(module, mode):
    """expect(n): below the switch nothing loads; at the switch they load on a thread of their
    own while the numpy path goes on, and the first call that reaches the switch finds them."""
    switch, _ = SETS[module]
    code = ("import importlib, threading, time\n"
            f"k = importlib.import_module({module!r})\n"
            f"n = k.{switch}\n"
            "k.expect(n - 1)\n"
            "print(k.loaded(), threading.active_count())\n"
            "k.expect(n)\n"
            "t = time.time()\n"
            "while not k.loaded() and time.time() - t < 120 and k.enabled():\n"
            "    time.sleep(0.01)\n"
            "print(k.loaded(), k.use_for(1))\n")
    out = printed(code, APCG_KERNELS=mode).split()
    assert out[:2] == ["False", "1"]  # below the switch: no thread, nothing loaded
    assert out[2:] == (["True", "True"] if mode == "" else ["False", "False"])


def test_work_goes_on_on_numpy_while_expect_loads_and_warm_comes_first():
    """While expect's thread loads (and warms) the kernels, calls take the numpy path, past
    the switch too, instead of waiting; the warm call gets the kernels before anyone else."""
    code = ("import threading, time\n"
            "from apcg_core.kernel_loader import KernelSet, Loader\n"
            "seen = []\n"
            "go = threading.Event()\n"
            "def compile():\n"
            "    go.wait(60)\n"
            "    return KernelSet(f=lambda: 1)\n"
            "def warm(k):\n"
            "    seen.append(('warm', loader.loaded(), k.f()))\n"
            "loader = Loader(compile, 'test kernels', 10)\n"
            "loader.expect(10, warm=warm)\n"
            "print(loader.loading(), loader.use_for(100), loader.use_for(100), loader.loaded())\n"
            "go.set()\n"
            "loader._loading.join(60)\n"
            "print(seen, loader.loading(), loader.use_for(1), loader.loaded())\n")
    out = printed(code, APCG_KERNELS="").splitlines()
    assert out[0].split() == ["True", "False", "False", "False"]
    assert out[1] == "[('warm', False, 1)] False True True"


def test_numba_loads_without_importing_scipy_and_scipy_still_imports_after():
    """The kernels use no linear algebra: numba's load does not pull in scipy (0.3 s and an
    OpenBLAS thread pool), the kernels work, and scipy imports as usual afterwards."""
    code = ("import sys\n"
            "import numpy as np\n"
            "from apcg_core.families import load_model, plus_kernels\n"
            "m = load_model(None)\n"
            "plus_kernels.expect(plus_kernels.SWITCH_CLOUDS, warm=m._warm_reader)\n"
            "plus_kernels._loader._loading.join(300)\n"
            "print(plus_kernels.loaded(), 'scipy' in sys.modules, 'numba' in sys.modules)\n"
            "c = m.conditions(['A320neo'], [[6000.0, 0.06, 0.03, 0.2, 0.0]])\n"
            "t = m.repeated_conditions(c, 1)\n"
            "print(len(m.clouds_of(t, m.sheets(t), compiled=True)) > 0)\n"
            "import scipy.linalg\n"
            "print(scipy.linalg.norm(np.ones(4)))\n")
    out = printed(code, APCG_KERNELS="").split()
    assert out == ["True", "False", "True", "True", "2.0"], out
