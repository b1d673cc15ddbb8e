#!/usr/bin/env bash
# The LiDAR photon ladder (issue 51): every depth decoder at four light levels, without ambient
# light and at SBR 1, on the LiDAR sets of scripts/ood.sh (scripts/ood_sets.sh) and the
# Middlebury motorcycle, through the codes of one zoo entry; one table of the first return's
# median error in bins · share within half a bin.
#
#   scripts/lidar_ladder.sh [OUT] [--decoder NAME …]
#
# Defaults: the fit (depth-fit), the fit pooled by likeness (depth-fit-pooled), zoo:unet-lidar-evidence-8k,
# zoo:unet-lidar-evidence-capped2, zoo:unet-lidar-evidence-wide2 and zoo:unet-lidar-matched through the designed codes. SIZE (64x64), ITEMS (8), LIGHT (0.8,0.1,0.02,0.005) come from the environment.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-lidar-ladder}
shift || true
SIZE=${SIZE:-64x64}
ITEMS=${ITEMS:-8}
LIGHT=${LIGHT:-0.8,0.1,0.02,0.005}
CODES=${CODES:-zoo/unet-lidar-designed/codes.json}
cargo build --release --locked
B=target/release/tcsense
. scripts/ood_sets.sh
mkdir -p "$OUT"
lidar_test_sets "$OUT/" 80 >/dev/null
motorcycle_set "$OUT" >/dev/null
decoders=("$@")
[ ${#decoders[@]} -eq 0 ] && decoders=(--decoder depth-fit --decoder depth-fit-pooled --decoder zoo:unet-lidar-evidence-8k --decoder zoo:unet-lidar-evidence-capped2 --decoder zoo:unet-lidar-evidence-wide2 --decoder zoo:unet-lidar-matched)
for s in standard far near textures dense-sheet lidar-test-motorcycle; do
  split=train
  [ "$s" = lidar-test-motorcycle ] && split=test
  for sbr in none 1; do
    extra=()
    [ "$sbr" != none ] && extra=(--sbr "$sbr")
    $B eval --dataset "$OUT/$s" --split "$split" --items "$ITEMS" --codes "$CODES" --irf physical --seed 5 --light "$LIGHT" "${extra[@]}" \
      "${decoders[@]}" -o "$OUT/ladder-$s-sbr$sbr.json" >/dev/null
  done
done
python3 - "$OUT" <<'PY'
import json, sys, glob, os
out = sys.argv[1]
rows, levels = {}, []
for f in sorted(glob.glob(f"{out}/ladder-*.json")):
    s = os.path.basename(f)[len("ladder-"):-5]
    for r in json.load(open(f)):
        l = r["light"]["signal_fraction"]
        levels += [l] if l not in levels else []
        rows.setdefault((s, r["decoder"]), {})[l] = r
print("| set | decoder | " + " | ".join(str(l) for l in levels) + " |")
print("|---|---|" + "---|" * len(levels))
def cell(r, bin_m):
    med, within = r and r["depth_median_m"][0], r and r["depth_within_half_bin"][0]
    return "–" if med is None or within is None else f"{med / bin_m:.2f} · {within * 100:.0f} %"
def bin_of(s):
    m = json.load(open(f"{out}/{s.rsplit('-sbr', 1)[0]}/manifest.json"))
    return 299792458.0 * m["bin_width_s"] / 2
for (s, d), v in rows.items():
    print(f"| {s} | {d} | " + " | ".join(cell(v.get(l), bin_of(s)) for l in levels) + " |")
PY
