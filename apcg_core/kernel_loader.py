"""When the core's compiled loops (numba) are loaded: one mechanism for every set of them.

A set of compiled kernels (``apcg_core/sensor/kernels.py`` for the photon stage,
``apcg_core/families/plus_kernels.py`` for the APCG+ reader, ``dataset_builder/kernels.py`` for
the build's rays) sits beside the numpy code it replaces and gives the same bytes. The core
imports with numpy alone (the add-on runs in Blender's Python, which has no numba): numba is
imported only inside :meth:`Loader.load`, when it is installed and allowed, and the numpy code
runs otherwise, same bytes, slower.

``APCG_KERNELS`` in the environment is read for every set: ``numpy`` never loads them,
``compiled`` loads them at the first call; otherwise a process starts on numpy and loads them
once it has put a set's own amount of work (its switch: hits, clouds, ...) through the numpy
path: loading costs about 0.5 s, so a short run never pays it and a long one pays it once
(rent, then buy). A caller that knows how much work is coming says so (:meth:`Loader.expect`):
when that reaches the switch, the set is loaded at once on a thread of its own, beside the
first work on the numpy path, instead of stalling the work that reaches the switch. Work keeps
to the numpy path until that thread is done (it never waits for it), and the thread also makes
the caller's first call (``warm``): numba loads each compiled function from its cache, and sets
up its runtime, at a function's first call in a process (about 0.3 s of CPU here, most of it
holding the GIL), which the first block of real work would otherwise pay while the other
threads wait on numba's compiler lock.
"""

from __future__ import annotations

import contextlib
import gc
import importlib.util
import os
import threading

ENV = "APCG_KERNELS"  # "numpy": never use the compiled kernels; "compiled": from the start


def mode() -> str:
    return os.environ.get(ENV, "").strip().lower()


class KernelSet:
    """The compiled functions of one set, as attributes."""

    def __init__(self, **fns) -> None:
        self.__dict__.update(fns)


class Loader:
    """One set of kernels: ``compile`` (imports numba, returns a :class:`KernelSet`) is run
    once, at the first call that should take the compiled path; ``what`` names the set in the
    message when numba is missing; ``switch``: the units of work (hits, clouds, ...) a process
    puts through the numpy path before it loads them. A set's module exposes the loader's
    methods as its own functions (``enabled``, ``loaded``, ``use_for``, ``require``,
    ``expect``)."""

    def __init__(self, compile, what: str, switch: int) -> None:
        self._compile = compile
        self.what = what
        self.switch = switch
        self._kernels = None  # the compiled functions, once loaded; False when numba is missing
        self._numpy_work = 0  # work this process put through the numpy path before loading
        self._lock = threading.Lock()  # readers run in threads: compiled once
        self._loading: threading.Thread | None = None

    def enabled(self) -> bool:
        """Whether this process may use the compiled kernels (numba installed, not turned
        off)."""
        if mode() == "numpy":
            return False
        if self._kernels is None:
            return importlib.util.find_spec("numba") is not None
        return self._kernels is not False

    def loaded(self) -> bool:
        return self._kernels is not None and self._kernels is not False

    def use_for(self, n: int) -> bool:
        """Whether a call doing ``n`` units of work should take the compiled path (loading the
        kernels if it is time to: ``switch`` units on the numpy path, or ``compiled`` in the
        environment); counts the work toward ``switch`` when not."""
        switch = self.switch
        if not self.enabled():
            return False
        if self.loaded():
            return True
        if self.loading() and mode() != "compiled":  # expect's thread: never wait for it
            self._numpy_work += n
            return False
        if mode() == "compiled" or self._numpy_work + n >= switch:
            return self.load() is not False
        self._numpy_work += n
        return False

    def expect(self, n: int, warm=None) -> None:
        """``n`` units of work are coming: when they reach the switch (or ``compiled`` is set),
        start loading the kernels now, on a thread of their own, so that they load while the
        first work runs on the numpy path (the same bytes; :meth:`use_for` does not wait for
        them unless ``compiled`` is set). ``warm(kernels)``: a first call of the kernels with
        the argument types the caller's work will pass, made on that thread before the kernels
        are handed out (an exception in it is the work's to meet: it is dropped here)."""
        if (self._loading is not None or self.loaded() or not self.enabled()
                or (n < self.switch and mode() != "compiled")):
            return
        self._loading = threading.Thread(target=self.load, args=(warm,),
                                         name=f"load {self.what}", daemon=True)
        self._loading.start()

    def loading(self) -> bool:
        """Whether :meth:`expect`'s thread is loading the kernels now."""
        return self._loading is not None and self._loading.is_alive() and not self.loaded()

    def load(self, warm=None):
        """The kernels, loaded if numba is importable (and ``warm``, a first call of them,
        made before they are handed out); False when numba is not importable."""
        if self._kernels is None:
            with self._lock, long_lived_objects(), numba_without_scipy():
                if self._kernels is None:
                    self._kernels = self._load(warm)
        return self._kernels

    def _load(self, warm):
        try:
            import numba  # noqa: F401
        except ImportError:
            return False
        kernels = self._compile()
        if warm is not None:
            try:
                warm(kernels)
            except Exception:  # noqa: BLE001 - the real call will say it
                pass
        return kernels

    def require(self) -> KernelSet:
        """The compiled kernels, loaded (numba must be importable)."""
        k = self.load()
        if k is False:
            raise ImportError(f"{self.what} need numba: pip install 'apcg[sim]'")
        return k


@contextlib.contextmanager
def long_lived_objects():
    """Around work that makes many objects that live as long as the process (numba's import
    and its first calls: ~60,000): no cyclic garbage collection while they are made, then
    every object there is moved out of the collector's sight (:func:`gc.freeze`). A
    collection of all generations scans every tracked object, holding the GIL: two of them
    during numba's load took 0.11 s of a 102,400-cloud `apcg generate` (gc.callbacks, stop
    51), and each later one would scan those objects again. Objects freed by their reference
    counts are freed as before; the collector runs again afterwards."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.collect(0)  # the new objects, once (cycles among them freed), then frozen
        gc.freeze()
        if enabled:
            gc.enable()


class _NoScipyOnThisThread:
    """An import finder that answers "no such module" for scipy and its modules, to imports
    made on one thread (:func:`numba_without_scipy`); every other thread imports as usual."""

    def __init__(self) -> None:
        self.thread = threading.get_ident()

    def find_spec(self, name, path=None, target=None):
        if threading.get_ident() == self.thread and name.split(".", 1)[0] == "scipy":
            raise ModuleNotFoundError(f"No module named {name!r} (numba's load, "
                                      "apcg_core.kernel_loader)", name=name)
        return None


@contextlib.contextmanager
def numba_without_scipy():
    """numba imports scipy when it is installed (the sim extra installs it), for np.dot and
    np.linalg in compiled code: scipy and scipy.linalg's BLAS, 0.25-0.37 s of CPU of the
    0.85-1.4 s a process spends loading the kernels here, and an OpenBLAS thread pool that
    spins. No kernel of this package uses linear algebra, so while numba loads (and makes its
    first calls) on this thread, scipy is not found there; numba then goes without its
    linear algebra in this process. A process that has imported scipy already is left as it
    is, and other threads import it as usual throughout."""
    import sys
    if "scipy" in sys.modules:
        yield
        return
    finder = _NoScipyOnThisThread()
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
