"""Record in a model's model.json the lidars it was measured on (``measured_lidars``, SPEC
section 1): each held-out lidar of a ``bench/lidar_heldout.py`` report other than the model's
own, with its mean MMD and faithfulness there, so ``apcg generate --lidar X`` can say when X
lies outside them.

    .venv/bin/python tools/record_measured_lidars.py apcg_core/models/default \
        docs/evaluation/lidars/heldout.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.io.dataset import write_atomic  # noqa: E402


def main(model_dir: str, report: str) -> int:
    meta_path = Path(model_dir) / "model.json"
    meta = json.loads(meta_path.read_text())
    record = json.loads(Path(report).read_text())
    own = meta["lidar"]
    measured = []
    for preset, rep in record["lidars"].items():
        if rep["lidar"] == own:
            continue
        if Path(rep["model"]).resolve() != Path(model_dir).resolve():
            raise SystemExit(f"{report}: {preset} scored {rep['model']}, not {model_dir}")
        measured.append({"faithfulness": {k: round(v, 3) for k, v in
                                          rep["mean"]["faithfulness"].items()},
                         "lidar": rep["lidar"], "mmd": round(rep["mean"]["mmd"], 5),
                         "pairs": rep["pairs"], "preset": preset,
                         "source": f"{report} (bench/lidar_heldout.py)"})
    meta["measured_lidars"] = measured
    write_atomic(meta_path, (json.dumps(meta, indent=1) + "\n").encode())
    names = ", ".join(m["preset"] for m in measured)
    print(f"{meta_path}: {len(measured)} measured lidars ({names})")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    raise SystemExit(main(sys.argv[1], sys.argv[2]))
