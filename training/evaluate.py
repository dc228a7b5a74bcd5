"""`apcg evaluate`: a model against the simulator on held-out conditions, the paper's way
(Fig. 17: mean MMD and JSD per slant-range band, aircraft and drones apart) and more honestly
(the cell-jitter floor, pairs with too few points flagged instead of averaged, point-count
ratios, per-type scores, the PointFlow-protocol Chamfer set metrics, and the faithfulness
score of :mod:`training.faithfulness` beside the point z-buffer's and embree 2 x 2's). Scoring
is :mod:`training.protocol`'s; this module writes the report.

    apcg evaluate --model DIR --data DIR -o REPORT [--pairs N] [--seed S] [--with-untrained]
        [--no-faithfulness]

Writes REPORT/metrics.json, REPORT/report.md and REPORT/fig17.png. Every number carries the
command that reproduces it.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from apcg_core.metrics import jsd

from . import protocol
from .data import DepthDataset
from .protocol import MAX_POINTS, band_of, draw_pairs


def evaluate(model, data_dir, n_pairs: int | None = protocol.DEFAULT_PAIRS, seed: int = 0,
             with_untrained: bool = False, progress: bool = False,
             faithfulness: bool = True) -> dict:
    """The protocol's report of ``model`` on the test half of ``data_dir``'s held-out split,
    with per-type scores, faithfulness and its references (unless ``faithfulness`` is False),
    and the untrained network's scores per band when asked."""
    pairs = draw_pairs(data_dir, n_pairs, seed, half="test")
    report = protocol.score(model, pairs, progress=progress, faithfulness=faithfulness)
    report["types"] = protocol.per_type(report)
    # what the dataset's clouds are (a sensor's photon clouds, or None: standard clouds) and
    # what the model learnt: the "standard" clouds and the floor below are the dataset's
    report["dataset_sensor"] = dataset_sensor(data_dir)
    report["model_sensor"] = model_sensor(model)
    if with_untrained:
        with tempfile.TemporaryDirectory() as tmp:
            fresh = protocol.score(protocol.untrained(model, Path(tmp), seed), pairs,
                                   floor=False, pointflow=False)
        for name, b in report["bands"].items():
            u = fresh["bands"][name]
            b["untrained"] = {k: u[k] for k in ("mmd", "jsd", "chamfer_m2", "points_generated",
                                                "no_score")}
        report["mean"]["untrained"] = fresh["mean"]
    return report


def dataset_sensor(data_dir) -> dict | None:
    """The sensor a dataset was built with (its header's ``sensor``: its clouds are that
    single-photon lidar's, noise included), or None: standard (ideal) clouds."""
    from apcg_core.io.dataset import read_header
    return read_header(data_dir).get("sensor")


def model_sensor(model) -> dict | None:
    """The sensor whose photon clouds ``model`` was trained on (model.json ``sensor``), or
    None: a model of standard clouds."""
    value = (getattr(model, "meta", None) or {}).get("sensor")
    return value if isinstance(value, dict) else None


def _sensor_name(sensor: dict | None) -> str:
    return "none" if sensor is None else repr(sensor.get("name") or "unnamed")


def sensor_mismatch_warning(data_dir, model) -> str | None:
    """One line when the dataset's clouds (a sensor's photon clouds, or standard clouds) are
    not of the kind the model makes (model.json ``sensor``): the scores and the floor would
    compare a model's clouds against clouds of another kind. None when they agree."""
    ours, theirs = dataset_sensor(data_dir), model_sensor(model)
    if json.dumps(ours, sort_keys=True) == json.dumps(theirs, sort_keys=True):
        return None
    what = (f"holds photon clouds of the sensor {_sensor_name(ours)} (built with --sensor; "
            "noise included)" if ours is not None else "holds standard (ideal) clouds")
    made = (f"photon clouds of the sensor {_sensor_name(theirs)} (its model.json 'sensor')"
            if theirs is not None else "standard (ideal) clouds")
    return (f"the dataset {data_dir} {what} but the model {getattr(model, 'directory', model)} "
            f"makes {made}: its clouds are scored against the dataset's as they are, and the "
            "floor is computed from the dataset's clouds")


def _kind(sensor: dict | None) -> str:
    return ("standard (ideal) clouds" if sensor is None
            else f"photon clouds of the sensor {_sensor_name(sensor)}")


def _clouds_said(report: dict) -> str:
    """The report's sentence on what the dataset's clouds (the reference) and the model's are."""
    if "dataset_sensor" not in report:  # a report from before it said so
        return ""
    ds, mine = report.get("dataset_sensor"), report.get("model_sensor")
    said = f"The dataset's clouds are {_kind(ds)}"
    if ds is not None:
        said += (" (built with --sensor, noise included): the standard clouds and the floor "
                 "below are those")
    if json.dumps(ds, sort_keys=True) == json.dumps(mine, sort_keys=True):
        return said + "; the model makes the same kind."
    return said + f"; the model makes {_kind(mine)}, not that kind."


def _fmt(v, digits=3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def markdown(report: dict) -> str:
    lines = [f"# APCG evaluation: {report['model']}", "",
             f"Reproduce: `{report['command']}`", "",
             f"{report['pairs']} held-out pairs ({report['pairs_asked']} asked; the "
             f"{report['half']} half of the test split of `{report['dataset']}`, stratified "
             f"by band, seed {report['seed']}); JSD over {report['protocol']['jsd_bins']}^3 "
             f"bins; clouds subsampled to at most {report['protocol']['max_points']} points; "
             f"pairs with fewer than {report['protocol']['min_points']} points on a side are "
             "flagged (low) and not averaged. "
             "Floor: the standard cloud against its own copy jittered inside each resolution "
             "cell, the best any generator can hope to score. Untrained: the same network "
             "freshly initialised (when asked for). 1-NNA-CD below 0.5 on these paired sets "
             "means each generated cloud lies nearest its own condition's reference."
             + (" " + _clouds_said(report) if "dataset_sensor" in report else ""), "",
             "| band | pairs | low | empty | pts std | pts gen | MMD | MMD floor | MMD untrained "
             "| JSD | JSD floor | JSD untrained | Chamfer (m^2) | COV-CD | 1-NNA-CD |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, b in report["bands"].items():
        pf = b.get("pointflow", {})
        u = b.get("untrained", {})
        lines.append(
            f"| {name} | {b['pairs']} | {b['low_points']} | {b['no_score']} | "
            f"{b['points_standard']:.0f} | {b['points_generated']:.0f} | {_fmt(b['mmd'])} | "
            f"{_fmt(b['floor']['mmd'])} | {_fmt(u.get('mmd'))} | {_fmt(b['jsd'])} | "
            f"{_fmt(b['floor']['jsd'])} | {_fmt(u.get('jsd'))} | {_fmt(b['chamfer_m2'], 2)} | "
            f"{_fmt(pf.get('cov_cd'), 2)} | {_fmt(pf.get('nna_cd'), 2)} |")
    lines += faithfulness_table(report)
    if report.get("types"):
        lines += ["", "Per type (catalog name):", "",
                  "| type | pairs | scored | pts std | pts gen | MMD | JSD |",
                  "|---|---|---|---|---|---|---|"]
        for name, t in report["types"].items():
            lines.append(f"| {name} | {t['pairs']} | {t['scored']} | "
                         f"{t['points_standard']:.0f} | {t['points_generated']:.0f} | "
                         f"{_fmt(t['mmd'])} | {_fmt(t['jsd'])} |")
    sec = report["seconds"]
    lines += ["", f"Took {sec['total']} s (generation {sec['generate']} s"
              + (f", faithfulness {sec['faithfulness']} s" if "faithfulness" in sec else "")
              + ")."]
    return "\n".join(lines) + "\n"


def _share(f: dict | None) -> str:
    if not f or f.get("share") is None:
        return "-"
    return (f"{100 * f['share']:.0f}% ({100 * f['share_vs_yaw']:.0f}% / "
            f"{100 * f['share_vs_other_type']:.0f}%)")


def _ratio(b: dict) -> str:
    return " / ".join(_fmt(v, 2) for v in b["points_ratio_p10_p50_p90"])


def faithfulness_table(report: dict) -> list[str]:
    """Markdown lines: per band the model's MMD, JSD, point-count ratio and faithfulness beside
    the references' MMD and faithfulness (nothing when the report has no faithfulness)."""
    refs = report.get("references")
    if not refs:
        return []
    m = report["mean"]["faithfulness"]
    pct = {k: "-" if v is None else f"{100 * v:.0f}%" for k, v in m.items()}
    lines = ["", "Faithfulness (SPEC section 9): the share of scorable pairs whose generated "
             "cloud is closer (MMD) to its own standard cloud than to both decoys, the same "
             "type at yaw +-45 deg and a type of another category at the same condition (in "
             "brackets: closer than the yaw decoy / than the other type). Pairs whose standard "
             f"cloud has fewer than {report['protocol']['min_points']} points are not scorable; "
             "a generated cloud with fewer is not faithful. The references make their clouds by "
             "simulation on the same pairs: the paper's point z-buffer and embree with 2 x 2 "
             "rays per cell. Points ratio: generated / standard points, p10 / median / p90. "
             f"Mean share over bands: {pct['all']} (aircraft {pct['aircraft']}, drones "
             f"{pct['drone']}).", "",
             "| band | pairs | scorable | too few pts | MMD | JSD | points ratio | faithful "
             + "".join(f"| {r} MMD | {r} faithful " for r in refs) + "|",
             "|" + "---|" * (8 + 2 * len(refs))]
    for name, b in report["bands"].items():
        f = b["faithfulness"]
        cells = [name, str(b["pairs"]), str(f["scorable"]), str(f["too_few_points"]),
                 _fmt(b["mmd"]), _fmt(b["jsd"], 2), _ratio(b), _share(f)]
        for r in refs.values():
            rb = r["bands"].get(name, {})
            cells += [_fmt(rb.get("mmd")), _share(rb.get("faithfulness"))]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(report: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), constrained_layout=True)
    for col, kind in enumerate(("aircraft", "drone")):
        names = [n for n in report["bands"] if n.startswith(kind)]
        if not names:
            continue
        x = np.arange(len(names))
        for row, metric in enumerate(("mmd", "jsd")):
            ax = axes[row, col]
            val = [report["bands"][n][metric] or np.nan for n in names]
            floor = [report["bands"][n]["floor"][metric] or np.nan for n in names]
            ax.plot(x, val, "o-", label="APCG")
            ax.plot(x, floor, "s--", label="cell-jitter floor")
            if all("untrained" in report["bands"][n] for n in names):
                ax.plot(x, [report["bands"][n]["untrained"][metric] or np.nan for n in names],
                        "^:", label="untrained network")
            ax.set_xticks(x, [n.split(" ", 1)[1] for n in names], rotation=20)
            ax.set_title(f"{kind}: {metric.upper()}" + (
                f" ({report['protocol']['jsd_bins']}^3 bins)" if metric == "jsd" else ""))
            ax.grid(alpha=0.3)
            ax.legend()
    fig.suptitle("APCG vs the simulator per slant-range band (paper Fig. 17)")
    from apcg_core.io.atomic import atomic_path
    with atomic_path(path, ".part" + Path(path).suffix) as tmp:  # matplotlib reads the format
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def write_report(report: dict, out_dir) -> Path:
    from apcg_core.io.dataset import write_atomic
    out = Path(out_dir)
    write_atomic(out / "metrics.json", (json.dumps(report, indent=1) + "\n").encode())
    write_atomic(out / "report.md", markdown(report).encode())
    plot(report, out / "fig17.png")
    return out


def jsd_bins_study(model, data_dir, bins=(4, 6, 8, 12, 16, 20, 28), per_band: int = 40,
                   seed: int = 0, shift_m: float = 5.0) -> dict:
    """How JSD separates a good cloud from a wrong one at each bin count, per band (how
    ``protocol.JSD_BINS`` was chosen; on the validation half).

    For each held-out standard cloud: its cell-jittered copy (the floor: as good as a generator
    can be), the same copy moved ``shift_m`` metres down-range (wrong by a few cells), and the
    model's cloud. ``best`` maximises the smallest per-band gap between wrong and floor."""
    pairs = draw_pairs(data_dir, per_band * 9, seed, half="validation")
    ds = pairs.ds
    gen, _ = protocol.generate(model, pairs)
    rows: dict = {}
    for j, i in enumerate(pairs.idx):
        std = ds.standard_cloud(int(i))
        jit = protocol.jittered(ds, int(i), seed + j)
        los = std.mean(axis=0) / np.linalg.norm(std.mean(axis=0)) if len(std) else 0.0
        wrong = jit + shift_m * los
        for c in bins:
            r = rows.setdefault(pairs.bands[j], {}).setdefault(
                c, {"floor": [], "wrong": [], "model": []})
            for key, other in (("floor", jit), ("wrong", wrong), ("model", gen[j])):
                v = jsd(std, other, bins=c, max_points=MAX_POINTS, seed=seed + j)
                if v is not None:
                    r[key].append(v)
    table = {band: {str(c): {k: float(np.mean(v)) if v else None for k, v in d.items()}
                    for c, d in per_c.items()} for band, per_c in rows.items()}
    gaps = {c: min((table[b][str(c)]["wrong"] or 0) - (table[b][str(c)]["floor"] or 0)
                   for b in table) for c in bins}
    sizes = np.diff(ds.offsets)
    return {**pairs.record(), "bins": table, "min_gap": {str(c): g for c, g in gaps.items()},
            "best": int(max(gaps, key=gaps.get)), "shift_m": shift_m,
            "points": {b: float(np.mean([sizes[i] for i, bi in zip(pairs.idx, pairs.bands,
                                                                    strict=True) if bi == b]))
                       for b in table}}


__all__ = ["DepthDataset", "band_of", "dataset_sensor", "evaluate", "jsd_bins_study",
           "markdown", "model_sensor", "plot", "sensor_mismatch_warning", "write_report"]
