#!/usr/bin/env bash
# Learned codes (deep sensing) against the best of 20 random code sets (`codes select`, the
# paper's method) under the same constraints (4 taps, 2x2, L = 32, tap + H 2 + W 2), for
# ADMM-Net on LiDAR and on FLIm (heterodyne K = 8), each trained for the same budget on the
# randomised data, noise on. Also: how far the relaxed codes were from feasible, and what the
# projection cost before and after fine-tuning.
#
#   scripts/learned_codes.sh [OUT]       (default OUT = learned-out; about 25 minutes on 2 cores)
#
# Budgets from the environment: SIZE (32x32), LIDAR_COUNT (300), FLIM_COUNT (200),
# LIDAR_EPOCHS (20), FLIM_EPOCHS (6), ITEMS (test items per set, 10).
# Results: OUT/learned.csv (set, codes, decoder metrics) and the table printed at the end.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-learned-out}
SIZE=${SIZE:-32x32}
LIDAR_COUNT=${LIDAR_COUNT:-300}
FLIM_COUNT=${FLIM_COUNT:-200}
LIDAR_EPOCHS=${LIDAR_EPOCHS:-20}
FLIM_EPOCHS=${FLIM_EPOCHS:-6}
ITEMS=${ITEMS:-10}
CONSTRAINTS="--taps 4 --block 2x2 --length 32 --tap-constraint --hamming 2 --window 2"

cargo build --release --locked
B=target/release/tcsense
mkdir -p "$OUT"

# data: randomised training sets, their test splits, and sets out of their distribution
$B dataset lidar --size "$SIZE" --force --count "$LIDAR_COUNT" --seed 2 -o "$OUT/lidar"
$B dataset lidar --size "$SIZE" --force --paper --count 120 --seed 11 -o "$OUT/lidar-paper"
$B dataset lidar --size "$SIZE" --force --count 120 --seed 12 --wall-range 0.93,0.97 --object-range 0.6,0.9 -o "$OUT/lidar-far"
$B dataset flim --size "$SIZE" --force --count "$FLIM_COUNT" --seed 2 -o "$OUT/flim"
$B dataset flim --size "$SIZE" --force --paper --count 120 --seed 11 -o "$OUT/flim-paper"
$B dataset flim --size "$SIZE" --force --paper --onset-ns 0 --count 120 --seed 12 -o "$OUT/flim-onset-0ns"

# codes: a random start, and the best of 20 random sets by TVAL3 MSE on each training set
$B codes generate $CONSTRAINTS --seed 1 -o "$OUT/start.json"
[ -f "$OUT/select-lidar.json" ] || $B codes select $CONSTRAINTS --dataset "$OUT/lidar" --split val --items 2 --candidates 20 -o "$OUT/select-lidar.json"
[ -f "$OUT/select-flim.json" ] || $B codes select $CONSTRAINTS --dataset "$OUT/flim" --split val --items 2 --candidates 20 -o "$OUT/select-flim.json"

T="$B train admm-net --preset cpu --seed 3"
for kind in lidar flim; do
  epochs=$LIDAR_EPOCHS
  [ "$kind" = flim ] && epochs=$FLIM_EPOCHS
  [ -f "$OUT/$kind-selected/model.bpk" ] || $T --dataset "$OUT/$kind" --codes "$OUT/select-$kind.json" --epochs "$epochs" -o "$OUT/$kind-selected"
  [ -f "$OUT/$kind-learned/model.bpk" ] || $T --dataset "$OUT/$kind" --codes "$OUT/start.json" --epochs "$epochs" --learn-codes -o "$OUT/$kind-learned"
  # the relaxed network with the projected codes, before fine-tuning
  rm -rf "$OUT/$kind-projected-before-finetune"
  cp -r "$OUT/$kind-learned/relaxed" "$OUT/$kind-projected-before-finetune"
  cp "$OUT/$kind-learned/codes.json" "$OUT/$kind-projected-before-finetune/codes.json"
done

echo "set,codes,decoder,items,mse,psnr_db,bounce1_rmse_m,bounce1_mae_m,bounce1_detection,bounce2_rmse_m,bounce2_mae_m,bounce2_detection,lifetime_mae_s,seconds_per_frame" > "$OUT/learned.csv"
evaluate() { # SET DATASET KIND CODES-NAME CODES-FILE DECODER…
  local set=$1 ds=$2 kind=$3 name=$4 codes=$5
  shift 5
  local grid=""
  [ "$kind" = flim ] && grid="--heterodyne 8"
  $B eval --dataset "$ds" --split test --items "$ITEMS" --codes "$codes" $grid --noise --seed 5 "$@" -o "$OUT/eval-$set-$name.json" >/dev/null
  tail -n +2 "$OUT/eval-$set-$name.csv" | sed "s|^|$set,$name,|; s|admm-net:$OUT/[a-z-]*|admm-net|" >> "$OUT/learned.csv"
}
for kind in lidar flim; do
  for set in "$kind" "$kind-paper" $([ "$kind" = lidar ] && echo lidar-far || echo flim-onset-0ns); do
    evaluate "$set" "$OUT/$set" "$kind" selected "$OUT/select-$kind.json" --decoder tval3 --decoder "admm-net:$OUT/$kind-selected"
    evaluate "$set" "$OUT/$set" "$kind" learned "$OUT/$kind-learned/codes.json" --decoder tval3 --decoder "admm-net:$OUT/$kind-learned"
  done
  # the projection's cost: relaxed (hard argmax codes, may break the constraints), projected
  # before fine-tuning, and after (the learned row above)
  evaluate "$kind" "$OUT/$kind" "$kind" relaxed "$OUT/$kind-learned/relaxed/codes.json" --decoder "admm-net:$OUT/$kind-learned/relaxed"
  evaluate "$kind" "$OUT/$kind" "$kind" projected-before-finetune "$OUT/$kind-learned/codes.json" --decoder "admm-net:$OUT/$kind-projected-before-finetune"
  echo "$kind: relaxed codes' distance to feasibility per epoch (tap, Hamming, window violations):"
  column -s, -t < "$OUT/$kind-learned/relaxed/codes_log.csv"
  echo "$kind: projection: $(tr -d '\n ' < "$OUT/$kind-learned/relaxed/projection.json")"
done
echo
column -s, -t < "$OUT/learned.csv" | cut -c1-180
