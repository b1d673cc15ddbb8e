#!/usr/bin/env bash
# Deep sensing on the product (issue 53): the evidence networks' codes learned on the lifetime or
# range loss, across the photon ladder, against the same network trained as long on the
# designed codes; both on the photon ladder of the ood.sh sets (and, for LiDAR, the Middlebury
# motorcycle), each through its own codes.
#
#   scripts/deep_sensing_ladder.sh flim|lidar [OUT]
#
# FLIm: from zoo:lifetime-flim-evidence-fast, 4 relaxed + 2 fine-tuning epochs (learned) against 6
# epochs on the designed codes (control), on its recipe's data; about 45 minutes on 2 cores.
# LiDAR: from zoo:unet-lidar-evidence-wide2, 3 relaxed + 1 (learned) against 4 (control), 600
# training items of its recipe's data; about 50 minutes. One table of the first return's median
# error (bins) or the lifetime MAE (ns) per set and light level, learned against control.
# The ladders are scripts/lifetime_ladder.sh and scripts/lidar_ladder.sh (OUT/RUN-ladder). CODES_LR
# (0.05, the default of --codes-lr) from the environment; docs/results.md has FLIm at 0.05 and 0.01.
set -euo pipefail
cd "$(dirname "$0")/.."
DOMAIN=${1:?flim or lidar}
OUT=${2:-deep-sensing-$DOMAIN}
case "$DOMAIN" in
  flim | lidar) ;;
  *) echo "deep_sensing_ladder.sh: $DOMAIN: expected flim or lidar" >&2; exit 2 ;;
esac
cargo build --release --locked
B=$PWD/target/release/tcsense
mkdir -p "$OUT"
CODES_LR=${CODES_LR:-0.05}
case "$DOMAIN" in
  flim)
    ZOO=zoo/lifetime-flim-evidence-fast
    [ -d "$OUT/data" ] || $B dataset flim --count 1600 --size 64x64 --heterodyne 8 --tau-ns 0.2,10 --irf-fwhm-ns 0,2 --background 0,0.1 --seed 21 -o "$OUT/data"
    T=(train lifetime --input costs --dataset "$OUT/data" --codes "$ZOO/codes.json" --irf physical --epochs 6 --batch-size 8 --lr 5e-4 --max-train 640 --max-val 16 --crop 32x32 --signal 0.003,0.9 --ambient 0,1 --seed 7 --base-width 8 --points 64 --init-from "$ZOO")
    RELAXED=4 LADDER=scripts/lifetime_ladder.sh NET=lifetime
    ;;
  lidar)
    ZOO=zoo/unet-lidar-evidence-wide2
    [ -d "$OUT/data" ] || $B dataset lidar --count 2000 --size 64x64 --seed 101 -o "$OUT/data"
    T=(train unet --dataset "$OUT/data" --codes "$ZOO/codes.json" --irf physical --input costs --head score-volume --returns 2 --signal 0.002,0.9 --ambient 0,2 --crop 64x64 --epochs 4 --batch-size 4 --lr 1e-4 --seed 9 --max-train 600 --max-val 16 --init-from "$ZOO")
    RELAXED=3 LADDER=scripts/lidar_ladder.sh NET=unet
    ;;
esac
[ -f "$OUT/learned/model.bpk" ] || $B "${T[@]}" --learn-codes --relaxed-epochs "$RELAXED" --codes-lr "$CODES_LR" -o "$OUT/learned"
[ -f "$OUT/control/model.bpk" ] || $B "${T[@]}" -o "$OUT/control"
# the domain's photon ladder (its sets, levels, items and seed), each run through its own codes
for run in learned control; do
  CODES="$OUT/$run/codes.json" "$LADDER" "$OUT/$run-ladder" --decoder "$NET:$OUT/$run" >/dev/null
done
analyze=()
[ "$DOMAIN" = flim ] && analyze=(--heterodyne 8)
$B codes analyze "$OUT/control/codes.json" "$OUT/learned/codes.json" "${analyze[@]}" | grep -E "json:|alias|bound  " || true
python3 - "$OUT" "$DOMAIN" <<'PY'
import json, sys, glob, os
out, domain = sys.argv[1], sys.argv[2]
rows, levels = {}, []
for run in ("learned", "control"):
    for f in sorted(glob.glob(f"{out}/{run}-ladder/ladder-*.json")):
        s = os.path.basename(f)[len("ladder-"):-5]
        for r in json.load(open(f)):
            l = r["light"]["signal_fraction"]
            levels += [l] if l not in levels else []
            rows.setdefault(s, {}).setdefault(l, {})[run] = r
def value(r, s):
    if domain == "flim":
        return None if r["lifetime_mae_s"] is None else r["lifetime_mae_s"] * 1e9
    m = json.load(open(f"{out}/control-ladder/{s.rsplit('-sbr', 1)[0]}/manifest.json"))
    med = r["depth_median_m"][0]
    return None if med is None else med / (299792458.0 * m["bin_width_s"] / 2)
unit = "lifetime MAE (ns)" if domain == "flim" else "first return's median error (bins)"
print(f"{unit}: learned codes / designed codes (ratio)")
print("| set | " + " | ".join(str(l) for l in levels) + " |")
print("|---|" + "---|" * len(levels))
for s, v in sorted(rows.items()):
    cells = []
    for l in levels:
        a, b = (value(v[l][k], s) if k in v.get(l, {}) else None for k in ("learned", "control"))
        cells.append("–" if a is None or b is None else f"{a:.3f} / {b:.3f} ({a / b:.2f}×)")
    print(f"| {s} | " + " | ".join(cells) + " |")
PY
