#!/usr/bin/env bash
# A real Blender window (Debian's blender 3.4.1 under Xvfb) with the legacy add-on: Scan
# Animation on a fighter passing in front of an airliner, the sequence playing on the timeline;
# the window at frames 1, 3 and 5 side by side in one picture.
#   bash tools/screenshot_scan_animation.sh docs/scan_animation.png
# Needs: apt-get install blender python3-numpy xvfb (xdotool: the APCG tab open); the venv's matplotlib (the strip)
set -euo pipefail
OUT=$(realpath -m "${1:-docs/scan_animation.png}")
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'kill $XVFB 2>/dev/null || true; rm -rf "$WORK"' EXIT
DISPLAY_NUM=:96
Xvfb $DISPLAY_NUM -screen 0 1600x900x24 +extension GLX >"$WORK/xvfb.log" 2>&1 &
XVFB=$!
python3 "$ROOT/tools/build_addon.py" --out "$WORK/dist" --legacy-only >/dev/null
mkdir -p "$WORK/scripts/addons"
(cd "$WORK/scripts/addons" && python3 -m zipfile -e "$WORK"/dist/apcg-legacy-*.zip .)
blender -b --factory-startup --python-expr \
  "import bpy; bpy.ops.wm.save_as_mainfile(filepath='$WORK/start.blend')" >/dev/null 2>&1
DISPLAY=$DISPLAY_NUM BLENDER_USER_SCRIPTS="$WORK/scripts" blender --factory-startup \
  "$WORK/start.blend" -P "$ROOT/tools/screenshot_scan_animation.py" -- "$WORK/shot" \
  >"$WORK/blender.log" 2>&1 &
BL=$!
for _ in $(seq 300); do grep -q "APCG: sidebar region" "$WORK/blender.log" && break; sleep 0.1; done
read -r RX RY RW RH WH < <(sed -n 's/.*x=\([0-9]*\) y=\([0-9]*\) w=\([0-9]*\) h=\([0-9]*\) window h=\([0-9]*\).*/\1 \2 \3 \4 \5/p' "$WORK/blender.log")
sleep 0.5
# the tab strip runs down the region's right edge; APCG is the 4th tab (Item, Tool, View, APCG)
if command -v xdotool >/dev/null; then
  DISPLAY=$DISPLAY_NUM xdotool mousemove $((RX + RW - 13)) $((WH - RY - RH + 161)) click 1
fi
wait $BL || true
grep "APCG:" "$WORK/blender.log"
"$ROOT/.venv/bin/python" - "$WORK/shot" "$OUT" <<'PY'
import sys
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
shot, out = sys.argv[1], sys.argv[2]
fig, axes = plt.subplots(1, 3, figsize=(24, 4.9), dpi=100)
for k, (ax, f) in enumerate(zip(axes, (1, 3, 5))):
    ax.imshow(plt.imread(f"{shot}_{k}.png"))
    ax.set_title(f"timeline frame {f}", fontsize=14)
    ax.axis("off")
fig.tight_layout()
fig.savefig(out)
PY
test -s "$OUT"
