"""What every model family's runtime shares: a model's type table and condition space read from
its ``model.json`` (:class:`ModelTypes`, the base of every family's model), the result of
generating, opening any model directory by the family that made it (:func:`load_model`), ONNX
helpers, and conditions from a CSV file. Numpy alone; onnxruntime where a model runs.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..condition import NOISE_DIM, Condition, ConditionSpace
from ..errors import InputError, check_int
from ..lidar import LidarParams, lidar_from_table
from ..typetable import Conditions, TypeTable, each_once
from .registry import family_of, get_family, read_model_meta

DEFAULT_MODEL_DIR = Path(__file__).parent.parent / "models" / "default"
RUNTIMES = ("auto", "onnx", "torch")


def default_model_dir() -> Path:
    return DEFAULT_MODEL_DIR


@dataclass
class GenerationResult:
    cloud: PointCloud  # stacked; cloud.sample indexes rows of ``conditions``
    images: np.ndarray  # (N, H, W) denormalised depth images (empty for point-set families)
    conditions: Conditions  # the condition of each cloud, in the model's type table

    @property
    def table(self) -> np.ndarray:
        return self.conditions.table


class ModelTypes:
    """What every model knows of its types and conditions (from its model.json): the base of
    every family's model. ``types`` is the model's :class:`TypeTable`; a condition from
    elsewhere reaches the model as :class:`Conditions` and is mapped into it by name."""

    directory: Path
    meta: dict
    types: TypeTable
    space: ConditionSpace
    lidar: LidarParams

    def __init__(self, directory=None) -> None:
        """A model's type table and condition space alone (no network loaded)."""
        self._read_model_json(directory)

    def _read_model_json(self, directory) -> None:
        self.directory = Path(directory) if directory else DEFAULT_MODEL_DIR
        self.meta = read_model_meta(self.directory)
        try:
            self.space = ConditionSpace.from_dict(self.meta["condition_space"])
            self.lidar = LidarParams.from_dict(self.meta["lidar"])
        except KeyError as exc:
            raise InputError(f"{self.directory / 'model.json'} is incomplete: it lacks "
                             f"{exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            raise InputError(f"{self.directory / 'model.json'} is incomplete ({exc!r})") from exc
        except InputError as exc:  # a value refused: say which file holds it
            raise InputError(f"{self.directory / 'model.json'}: {exc}") from exc
        self.types = TypeTable.from_records(self.meta["types"],
                                            owner=f"model {self.directory}")
        self._check_types_fill_space()
        self._check_sensor_record()

    def _check_types_fill_space(self) -> None:
        """The condition space scales the type code over ``n_types`` codes and names its drone
        types by code: a types table of another length (one cut by hand, say) would scale
        every type's nu wrongly or leave a drone code with no type; refused naming the file."""
        n, have = self.space.n_types, len(self.types)
        if n != have:
            past = [t for t in self.space.drone_types if t >= have]
            extra = (f" (its drone_types {past} name codes past the table)" if past else "")
            raise InputError(f"{self.directory / 'model.json'}: its condition_space has "
                             f"n_types {n} but its types table lists {have}{extra}: the "
                             f"model's files and model.json disagree; {_BROKEN}")

    def _check_sensor_record(self) -> None:
        value = self.meta.get("sensor")
        if value is not None and not (isinstance(value, dict) and value):
            raise InputError(f"{self.directory / 'model.json'}: 'sensor' must be the table of "
                             f"the sensor whose photon clouds the model learned, got {value!r}")

    @property
    def sensor(self) -> dict | None:
        """The sensor whose photon clouds the model was trained on (model.json ``sensor``,
        the training dataset header's sensor table), or None: a model of standard (ideal)
        clouds. A model with one already draws that sensor's photons."""
        return self.meta.get("sensor")

    def refuse_sensor(self, sensor, option: str = "--sensor") -> None:
        """Refuse a photon stage (``sensor``, not None) on the clouds of a model trained on a
        sensor's photon clouds: they would get a second sensor's photons on top of the
        first's."""
        if sensor is None or self.sensor is None:
            return
        ours = self.sensor.get("name") or "a sensor"
        asked = getattr(sensor, "name", None) or "a sensor"
        raise InputError(f"{option} ({asked}) not accepted with {self.directory}: that model "
                         f"was trained on photon clouds of {ours!r} (its model.json 'sensor'), "
                         "so its clouds already carry that sensor's photons; generate without "
                         f"{option}, or with a model trained on standard clouds")

    def meta_flag(self, key: str, default: bool) -> bool:
        """A true/false setting of model.json (``default`` when absent): a JSON boolean, or
        refused naming the file (the text "false" is not taken for true)."""
        value = self.meta.get(key, default)
        if not isinstance(value, bool):
            raise InputError(f"{self.directory / 'model.json'}: {key!r} must be true or false "
                             f"(a JSON boolean), got {value!r}")
        return value

    def meta_tau(self) -> float:
        """model.json's ``tau`` (the family's DEFAULT_TAU when absent), checked by the
        family's own ``check_tau``; a refusal names the file."""
        value = self.meta.get("tau", self.DEFAULT_TAU)
        try:
            if isinstance(value, bool):
                raise InputError(f"tau must be a number, got {value!r}")
            return self.check_tau(value)
        except InputError as exc:
            raise InputError(f"{self.directory / 'model.json'}: {exc}") from exc

    # Whether `apcg teach` can add a type to a model of this family: True or False where the
    # family's model knows; None: ask the family as registered (training's family object has
    # a ``teach`` where it can, and the core alone teaches nothing).
    TEACHABLE: bool | None = None

    def can_be_taught(self) -> bool:
        """Whether `apcg teach` takes this model (the test `apcg teach` itself makes)."""
        if self.TEACHABLE is not None:
            return self.TEACHABLE
        try:
            family = get_family(self.family)
        except InputError:
            return False
        return callable(getattr(family, "teach", None))

    # Whether the family draws at any lidar's cells (APCG+ reads its sheet at them), or only
    # at the lidar it was trained on (the cGAN's fixed H x W image; the baselines' point counts).
    ANY_LIDAR = False
    # Whether a cloud depends on the seed (a family that draws noise: --count gives that many
    # different clouds a condition), or is a function of the condition alone (APCG+).
    SEEDED = True

    @property
    def trained_lidar(self) -> LidarParams:
        """The lidar the model was trained on (model.json ``lidar``)."""
        return LidarParams.from_dict(self.meta["lidar"])

    def measured_lidars(self) -> list[LidarParams]:
        """The lidars the model was measured on: its training lidar and model.json's
        ``measured_lidars`` (each ``{"lidar": {...}, "source": ...}``, issue 33)."""
        out = [self.trained_lidar]
        for i, rec in enumerate(self.meta.get("measured_lidars") or []):
            table = rec.get("lidar") if isinstance(rec, dict) else None
            out.append(lidar_from_table(table, source=f"{self.directory / 'model.json'} "
                                                      f"measured_lidars[{i}]"))
        return out

    def use_lidar(self, lidar: LidarParams) -> None:
        """Generate at ``lidar``'s cells from now on; a family that cannot is refused."""
        if lidar == self.lidar:
            return
        if not self.ANY_LIDAR:
            raise InputError(f"a {self.family} model draws at the lidar it was trained on only "
                             f"({self.trained_lidar.describe()}), not at {lidar.describe()}; "
                             "an apcg-plus model draws at any lidar (the shipped default)")
        self.lidar = lidar

    def lidar_warning(self, lidar: LidarParams) -> str | None:
        """One line when ``lidar``'s cells or bin lie outside the span of the lidars the model
        was measured on (each of r_alpha, r_beta, r_r against its measured min..max)."""
        measured = self.measured_lidars()
        out = []
        for key in ("r_alpha_deg", "r_beta_deg", "r_r_m"):
            vals = [m.to_dict()[key] for m in measured]
            v = lidar.to_dict()[key]
            lo, hi = min(vals), max(vals)
            if not lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9):
                span = f"{lo:.6g}" if lo == hi else f"{lo:.6g}..{hi:.6g}"
                out.append(f"{key} {v:.6g} (measured: {span})")
        if not out:
            return None
        return (f"the lidar {lidar.describe()} lies outside what the model {self.directory} "
                f"was measured on: {'; '.join(out)}; its clouds there are unmeasured")

    @property
    def family(self) -> str:
        return str(self.meta.get("family", "cgan"))

    def type_name(self, key) -> str:
        """The catalog name of ``key``: a name this model knows, or a catalog index."""
        if isinstance(key, str) and key in self.types:  # any spelling: its one name
            return self.types.names[self.types.code(key)]
        from ..catalog.catalog import default_catalog, index_key
        if index_key(key) is not None:
            return default_catalog().get(key).name  # the catalog reads its own indices
        try:
            return self.types.names[self.types.code(key)]  # refuses, naming what it knows
        except InputError as exc:
            raise InputError(f"{exc}{self._teach_hint(key)}") from None

    def stale_meshes(self, names) -> list[str]:
        """One line for each of type ``names`` that this model learned from a mesh the catalog
        no longer holds under its name (its type record's ``mesh_sha256``, a user type's,
        against :meth:`Catalog.mesh_record` now: `catalog add --force` replaced it since the
        model was trained or taught). The model still draws the mesh it learned."""
        from ..catalog.catalog import default_catalog
        out = []
        for name in dict.fromkeys(names):
            learned = self.types.records[self.types.code(name)].get("mesh_sha256")
            if learned is None:
                continue
            try:
                now = default_catalog().mesh_record(name).get("mesh_sha256")
            except InputError:  # no longer in the catalog: nothing to compare
                continue
            if now != learned:
                out.append(f"{self.directory} learned {name!r} from another mesh than the "
                           f"catalog holds now (replaced since: its mesh_sha256 {learned[:12]}... "
                           f"against {str(now)[:12]}...); its clouds are of the mesh it "
                           f"learned: `apcg teach --model MODEL --type {name!r}` from a model "
                           "without it teaches the new one")
        return out

    def _teach_hint(self, key) -> str:
        """For a catalog type this model was not trained on (a user's, mostly): how to make a
        model that knows it, instead of a list of the names it does."""
        from ..catalog.catalog import default_catalog
        try:
            name = default_catalog().get(key).name
        except InputError:
            return ""
        if not self.can_be_taught():
            return (f". {name!r} is in the catalog but not in this model ({self.directory}), "
                    f"and a {self.family} model cannot be taught a type: train a model on a "
                    f"dataset that has {name!r} (`apcg dataset build`, `apcg train`), or teach "
                    "it to an apcg-plus model (the shipped default)")
        return (f". {name!r} is in the catalog but not in this model ({self.directory}): "
                f"`apcg teach --model {self.directory} --type {name!r} -o NEW_MODEL` makes a "
                "model that knows it (README, Bring your own aircraft)")

    def conditions(self, names, pose) -> Conditions:
        """Conditions for type ``names`` (one per row; names or catalog indices) at ``pose``
        (N, 5) [r0 m, beta0, pitch, yaw, roll rad], in this model's type table."""
        names = [names] if isinstance(names, (str, int, np.integer)) else list(names)
        return Conditions.from_names(self.types, each_once(names, self.type_name), pose)

    def condition(self, type_key, range_m, elevation, pitch=0.0, yaw=0.0,
                  roll=0.0) -> Conditions:
        """One condition (radians, metres), checked physically and against this model's
        condition space (before anything is made of it: a refusal comes first)."""
        row = Condition(0, range_m, elevation, pitch, yaw, roll).as_array()[1:]
        conditions = self.conditions([type_key], row[None])
        self.space.check(conditions.table, where=lambda i, j: "the condition")
        return conditions

    def depth_length(self, codes) -> np.ndarray:
        return self.types.column("depth_length_m").astype(np.float64)[
            np.asarray(codes, dtype=np.int64)]

    def repeated_conditions(self, conditions: Conditions, count) -> np.ndarray:
        """``conditions`` mapped by name into this model's types, checked against its
        condition space, each row ``count`` times (the table the model generates from)."""
        if not isinstance(conditions, Conditions):
            raise InputError("a model generates from Conditions (rows with the type table "
                             "their codes refer to; see model.conditions(names, pose)), not "
                             f"a bare {type(conditions).__name__}")
        table = self.space.check(conditions.recoded(self.types))
        return np.repeat(table, check_int("count", count, 1), axis=0)

    def expect_clouds(self, n: int) -> None:
        """``n`` clouds are about to be asked of this model (``apcg generate`` says so once it
        has read the request): a family whose speed depends on the amount of work prepares for
        it here (APCG+ loads its compiled reader early). Nothing by default."""

    def result(self, cloud: PointCloud, images, table: np.ndarray) -> GenerationResult:
        return GenerationResult(cloud, images, Conditions(self.types, table))


def load_model(directory=None, runtime: str = "auto"):
    """The model in ``directory`` (default: the shipped one), opened by the family that made
    it (model.json ``family``), whatever that family is."""
    d = DEFAULT_MODEL_DIR if directory is None or directory == "" else directory
    if runtime not in RUNTIMES:
        raise InputError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
    name = family_of(d)  # checks that d is a model directory, naming it
    try:
        family = get_family(name)
    except InputError as exc:
        raise InputError(f"{Path(d) / 'model.json'}: {exc}") from exc
    _check_network_types(d)
    try:
        return family.load(Path(d), runtime=runtime)
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError,
            EOFError, FileNotFoundError, zipfile.BadZipFile) as exc:
        # a family's files that disagree with its model.json (a network of another shape, a
        # missing record, a foreign or truncated weights file): one line, not a traceback
        raise InputError(f"model directory {d} is damaged: its {name} files and its "
                         f"model.json disagree or are incomplete ({type(exc).__name__}: "
                         f"{_short(exc)}); {_BROKEN}") from exc


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 200 else text[:197] + "..."


def _check_network_types(directory) -> None:
    """A network built for n types (model.json ``net.n_types``) serves exactly the model's
    types: with more, a code past its table fails in the middle of generation; with fewer,
    every name is drawn as another type's."""
    meta = read_model_meta(directory)
    net, types = meta.get("net"), meta.get("types")
    if isinstance(net, dict) and isinstance(types, list) and "n_types" in net \
            and net["n_types"] != len(types):
        raise InputError(f"{Path(directory) / 'model.json'}: its network is built for "
                         f"{net['n_types']!r} types but it lists {len(types)}: "
                         f"{_BROKEN}")


_BROKEN = ("a partial or corrupt file: export the model again (`apcg export`), or copy it "
           "again from where it came")


def onnxruntime(needed_for: str = "generation needs onnxruntime: pip install onnxruntime"):
    """The onnxruntime module, imported with its usage telemetry off (the one import of it in
    the package; ``needed_for``: the message when it is not installed).

    onnxruntime 1.29 and later record every process's use in a SQLite file under
    ~/.cache/Microsoft/DeveloperTools/.onnxruntime (2.4 MB here) for upload to Microsoft
    (microsoft/onnxruntime pull requests 27379 and 29843), and sync it to disk at exit: with
    other processes writing, that sync waited 0.9 s for `apcg generate`'s 667 MB output
    (ext4 commits the pages with its journal; on a quiet machine it cost nothing measurable,
    docs/SCALE.md, stop 54). A generator run on a user's data writes nothing to their home
    and reports nothing anywhere; ``ORT_DISABLE_TELEMETRY`` (onnxruntime's own switch, read
    when its environment is created) is set to 1 unless the user set it."""
    os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
    try:
        import onnxruntime as ort
    except ImportError as exc:
        raise InputError(needed_for) from exc
    return ort


def onnx_session(path, options):
    """An onnxruntime session over ``path``; a file it cannot load is named, not a traceback."""
    ort = onnxruntime()

    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for bad files
        raise InputError(f"{path} cannot be loaded ({type(exc).__name__}): {_BROKEN}") from exc


def onnx_weights(path) -> dict:
    """name -> numpy array of every weight in an ONNX file (initializers, through the Identity
    aliases the exporter makes for tensors that happen to be equal)."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError as exc:
        raise InputError("reading ONNX weights into torch needs the onnx package: "
                         "pip install 'apcg[train]'") from exc
    try:
        m = onnx.load(str(path))
    except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
        raise InputError(f"{path} cannot be read as ONNX ({type(exc).__name__}): "
                         f"{_BROKEN}") from exc
    w = {i.name: numpy_helper.to_array(i).copy() for i in m.graph.initializer}
    for n in m.graph.node:
        if n.op_type == "Identity" and n.input[0] in w:
            w[n.output[0]] = w[n.input[0]]
    return w


def conditions_from_csv(path, model: ModelTypes) -> Conditions:
    """Rows ``type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg`` (header required; the
    type by catalog name, or catalog index), in the model's type table. A dataset's
    conditions.csv (its ``type_name`` column) is read as it is. The reading and its errors
    (file, line, column, value): :func:`apcg_core.condition.read_conditions_csv`."""
    from ..condition import read_conditions_csv
    names, pose, where = read_conditions_csv(path, model.type_name)
    conditions = model.conditions(names, pose)
    model.space.check(conditions.table, where=where)  # the model's ranges, by line and column
    return conditions


__all__ = ["NOISE_DIM", "RUNTIMES", "Conditions", "GenerationResult", "ModelTypes",
           "conditions_from_csv", "default_model_dir", "load_model", "onnx_session",
           "onnx_weights"]
