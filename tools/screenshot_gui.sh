#!/usr/bin/env bash
# A real Blender window (Debian's blender 3.4.1 under Xvfb) with the legacy add-on enabled, the
# APCG sidebar tab open and a scanned aircraft in view, saved as a screenshot.
#   bash tools/screenshot_gui.sh docs/addon_screenshot.png
# Needs: apt-get install blender python3-numpy xvfb xdotool
set -euo pipefail
OUT=$(realpath -m "${1:-docs/addon_screenshot.png}")
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'kill $XVFB 2>/dev/null || true; rm -rf "$WORK"' EXIT
DISPLAY_NUM=:97
Xvfb $DISPLAY_NUM -screen 0 1600x900x24 +extension GLX >"$WORK/xvfb.log" 2>&1 &
XVFB=$!
python3 "$ROOT/tools/build_addon.py" --out "$WORK/dist" --legacy-only >/dev/null
mkdir -p "$WORK/scripts/addons"
(cd "$WORK/scripts/addons" && python3 -m zipfile -e "$WORK"/dist/apcg-legacy-*.zip .)
blender -b --factory-startup --python-expr \
  "import bpy; bpy.ops.wm.save_as_mainfile(filepath='$WORK/start.blend')" >/dev/null 2>&1
# opening a file skips the splash screen
DISPLAY=$DISPLAY_NUM BLENDER_USER_SCRIPTS="$WORK/scripts" blender --factory-startup \
  "$WORK/start.blend" -P "$ROOT/tools/screenshot_gui.py" -- "$OUT" >"$WORK/blender.log" 2>&1 &
BL=$!
for _ in $(seq 100); do grep -q "APCG: sidebar region" "$WORK/blender.log" && break; sleep 0.1; done
read -r RX RY RW RH WH < <(sed -n 's/.*x=\([0-9]*\) y=\([0-9]*\) w=\([0-9]*\) h=\([0-9]*\) window h=\([0-9]*\).*/\1 \2 \3 \4 \5/p' "$WORK/blender.log")
# the tab strip runs down the region's right edge; APCG is the 4th tab (Item, Tool, View, APCG)
sleep 0.5
DISPLAY=$DISPLAY_NUM xdotool mousemove $((RX + RW - 13)) $((WH - RY - RH + 161)) click 1
wait $BL || true
grep "APCG:" "$WORK/blender.log"
test -s "$OUT"
