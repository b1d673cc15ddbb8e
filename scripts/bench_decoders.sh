#!/usr/bin/env bash
# Speed against accuracy of every decoder path (issue 45), as one table:
#
#   scripts/bench_decoders.sh [OUT]
#
# - frames/s: each deployment path end to end as a whole process (`tcsense infer` of an
#   exported zoo entry over a stack of FRAMES noisy frames of FRAME pixels — reading, decoding,
#   products, writing — or `tcsense reconstruct` for TVAL3), on the zoo's designed codes;
# - accuracy: `tcsense eval` of the same decoders on the OOD sets of scripts/ood_sets.sh
#   (ITEMS noisy items of SIZE pixels per set, and the Middlebury motorcycle): the first
#   return's median error (m) and the second return's detection for LiDAR, the lifetime MAE (ns)
#   for FLIm.
#
# FRAME (188x212), FRAMES (30), SIZE (64x64), ITEMS (8), ACCURACY (1) and SPEED (1) come from
# the environment.
# Writes OUT/speed.csv, OUT/accuracy.csv and OUT/decoders.md.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-bench-decoders}
FRAME=${FRAME:-188x212}
FRAMES=${FRAMES:-30}
ITEMS=${ITEMS:-8}
cargo build --release --locked
scripts/setup.sh >/dev/null
B=target/release/tcsense
PY=.venv/bin/python
mkdir -p "$OUT"
LIDAR=zoo/unet-lidar-designed
FLIM=zoo/lifetime-flim-designed

# the OOD sets (SIZE pixels) and the motorcycle; ACCURACY=0 keeps OUT/accuracy.csv of an
# earlier run and measures the speed only
SIZE=${SIZE:-64x64}
if [ "${ACCURACY:-1}" != 0 ]; then
. scripts/ood_sets.sh
lidar_test_sets "$OUT/lidar-" 80 >/dev/null
flim_test_sets "$OUT/flim-" 80 >/dev/null
motorcycle_set "$OUT" >/dev/null

# accuracy
echo "set,decoder,bounce1_median_m,bounce1_mae_m,bounce2_detection,bounce2_false_alarm,lifetime_mae_s" > "$OUT/accuracy.csv"
accuracy() { # SET DATASET CODES GRID... -- DECODERS...
  local set=$1 ds=$2 codes=$3
  shift 3
  $B eval --dataset "$ds" --split test --items "$ITEMS" --codes "$codes" --irf physical --noise --seed 5 "$@" -o "$OUT/eval-$set.json" >/dev/null
  $PY - "$OUT/eval-$set.csv" "$set" >> "$OUT/accuracy.csv" <<'PY'
import csv, sys
for r in csv.DictReader(open(sys.argv[1])):
    print(",".join([sys.argv[2], r["decoder"], r.get("bounce1_median_m", ""), r["bounce1_mae_m"], r["bounce2_detection"], r.get("bounce2_false_alarm", ""), r["lifetime_mae_s"]]))
PY
}
lidar_decoders=(--decoder depth-fit:1 --decoder depth-fit --decoder depth-fit-pooled --decoder "unet:zoo:unet-lidar-designed" --decoder "unet-raw:zoo:unet-lidar-designed" --decoder tval3)
for s in standard far near textures dense-sheet; do accuracy "lidar-$s" "$OUT/lidar-$s" "$LIDAR/codes.json" "${lidar_decoders[@]}"; done
accuracy lidar-motorcycle "$OUT/lidar-test-motorcycle" "$LIDAR/codes.json" "${lidar_decoders[@]}"
flim_decoders=(--heterodyne 8 --decoder lifetime-fit --decoder "lifetime:zoo:lifetime-flim-designed" --decoder tval3)
for s in standard onset-0ns onset-30ns irf-1.5ns long-lifetimes background; do accuracy "flim-$s" "$OUT/flim-$s" "$FLIM/codes.json" "${flim_decoders[@]}"; done
fi

# speed: stacks of FRAMES noisy frames of FRAME pixels (a few scenes, repeated); SPEED=0 keeps
# OUT/speed.csv of an earlier run
if [ "${SPEED:-1}" != 0 ]; then
$B dataset lidar --size "$FRAME" --count 12 --seed 41 --force -o "$OUT/lidar-frame" >/dev/null
$B dataset flim --size "$FRAME" --count 12 --heterodyne 8 --seed 42 --force -o "$OUT/flim-frame" >/dev/null
$B simulate --codes "$LIDAR/codes.json" --irf physical --cube "$OUT/lidar-frame/train/x_000.npy" --noise --seed 1 -o "$OUT/lidar-y.npy" >/dev/null
$B simulate --codes "$FLIM/codes.json" --heterodyne 8 --irf physical --cube "$OUT/flim-frame/train/x_000.npy" --noise --seed 1 -o "$OUT/flim-y.npy" >/dev/null
$PY - "$OUT" "$FRAMES" <<'PY'
import sys, numpy as np
out, n = sys.argv[1], int(sys.argv[2])
for kind in ("lidar", "flim"):
    y = np.load(f"{out}/{kind}-y.npy")
    np.save(f"{out}/{kind}-stack.npy", np.ascontiguousarray(np.stack([y[i % len(y)] for i in range(n)])))
    np.save(f"{out}/{kind}-two.npy", np.ascontiguousarray(y[:2]))
PY
$B export onnx --run "zoo:unet-lidar-designed" -o "$OUT/unet-lidar-designed.onnx" >/dev/null
$B export onnx --run "zoo:lifetime-flim-designed" -o "$OUT/lifetime-flim-designed.onnx" >/dev/null
echo "path,frames,seconds,frames_per_s" > "$OUT/speed.csv"
timed() { # NAME FRAMES COMMAND...
  local name=$1 n=$2
  shift 2
  local t0 t1
  t0=$(date +%s.%N)
  "$@" >/dev/null
  t1=$(date +%s.%N)
  $PY -c "import sys; s=float(sys.argv[3])-float(sys.argv[2]); print(f'{sys.argv[1]},{sys.argv[4]},{s:.3f},{int(sys.argv[4])/s:.1f}')" "$name" "$t0" "$t1" "$n" >> "$OUT/speed.csv"
}
U="$OUT/unet-lidar-designed.onnx"
L="$OUT/lifetime-flim-designed.onnx"
timed "depth-fit:1 (infer --depth-fit --returns 1)" "$FRAMES" $B infer --model "$U" --measurements "$OUT/lidar-stack.npy" --depth-fit --returns 1 -o "$OUT/o1"
timed "depth-fit (infer --depth-fit)" "$FRAMES" $B infer --model "$U" --measurements "$OUT/lidar-stack.npy" --depth-fit -o "$OUT/o2"
timed "depth-fit-pooled (infer --depth-fit --pool-like 15)" "$FRAMES" $B infer --model "$U" --measurements "$OUT/lidar-stack.npy" --depth-fit --pool-like 15 -o "$OUT/o2p"
timed "unet + range fit (infer)" "$FRAMES" $B infer --model "$U" --measurements "$OUT/lidar-stack.npy" -o "$OUT/o3"
timed "unet-raw (infer --no-range-fit)" "$FRAMES" $B infer --model "$U" --measurements "$OUT/lidar-stack.npy" --no-range-fit -o "$OUT/o4"
timed "tval3 + peaks (reconstruct tval3 then depth)" 2 bash -c "$B reconstruct tval3 --codes $LIDAR/codes.json --irf physical --measurements $OUT/lidar-two.npy -o $OUT/tv.npy && $B depth $OUT/tv.npy -o $OUT/tvd.npy"
timed "lifetime-fit (infer --lifetime-fit)" "$FRAMES" $B infer --model "$L" --measurements "$OUT/flim-stack.npy" --lifetime-fit --products lifetime,intensity -o "$OUT/o5"
timed "lifetime network (infer)" "$FRAMES" $B infer --model "$L" --measurements "$OUT/flim-stack.npy" -o "$OUT/o6"
timed "tval3 + reconvolution fit (reconstruct tval3 then lifetime)" 2 bash -c "$B reconstruct tval3 --codes $FLIM/codes.json --heterodyne 8 --irf physical --measurements $OUT/flim-two.npy -o $OUT/tvf.npy && $B lifetime $OUT/tvf.npy -o $OUT/tvl.npy"
fi

$PY - "$OUT" > "$OUT/decoders.md" <<'PY'
import csv, sys
out = sys.argv[1]
speed = {r["path"].split(" (")[0]: r for r in csv.DictReader(open(f"{out}/speed.csv"))}
acc = list(csv.DictReader(open(f"{out}/accuracy.csv")))
label = lambda d: d.replace("unet:zoo:", "unet + range fit: ").replace("unet-raw:zoo:", "unet-raw: ").replace("lifetime:zoo:", "lifetime network: ")
key = {"depth-fit:1": "depth-fit:1", "depth-fit": "depth-fit", "depth-fit-pooled": "depth-fit-pooled", "unet:zoo:unet-lidar-designed": "unet + range fit", "unet-raw:zoo:unet-lidar-designed": "unet-raw", "lifetime-fit": "lifetime-fit", "lifetime:zoo:lifetime-flim-designed": "lifetime network"}
f = lambda v, s=1, d=3: f"{float(v)*s:.{d}f}" if v not in ("", "NaN", "nan") else "–"
for kind, sets in (("lidar", ["standard", "far", "near", "textures", "dense-sheet", "motorcycle"]), ("flim", ["standard", "onset-0ns", "onset-30ns", "irf-1.5ns", "long-lifetimes", "background"])):
    decs = []
    for r in acc:
        if r["set"].startswith(kind + "-") and r["decoder"] not in decs:
            decs.append(r["decoder"])
    what = "first-return median (m) / second returns detected" if kind == "lidar" else "lifetime MAE (ns)"
    print(f"\n{kind.upper()} — {what}, and frames/s end to end at the frame size of speed.csv\n")
    print("| decoder | frames/s | " + " | ".join(sets) + " |")
    print("|---|---|" + "---|" * len(sets))
    for d in decs:
        k = key.get(d, "tval3 + peaks" if kind == "lidar" else "tval3 + reconvolution fit")
        fps = speed.get(k, {}).get("frames_per_s", "–")
        cells = []
        for s in sets:
            row = next((r for r in acc if r["set"] == f"{kind}-{s}" and r["decoder"] == d), None)
            if row is None:
                cells.append("–")
            elif kind == "lidar":
                cells.append(f"{f(row['bounce1_median_m'])} / {f(row['bounce2_detection'], 100, 0)} %" if s != "motorcycle" else f(row["bounce1_median_m"]))
            else:
                cells.append(f(row["lifetime_mae_s"], 1e9))
        print(f"| {label(d)} | {fps} | " + " | ".join(cells) + " |")
PY
cat "$OUT/decoders.md"
