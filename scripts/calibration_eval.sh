#!/usr/bin/env bash
# Decoders on a non-ideal sensor (5 % tap-gain mismatch, 2 % PRNU, dark offset with a pattern,
# a 25 % diffusion tail of 2 ns): decoded with the nominal model, after calibration from a noisy
# sweep, with perfect knowledge (the calibration of a noise-free sweep), after calibration +
# fine-tuning the zoo's LiDAR ADMM-Net for 10 minutes, and the ideal sensor for reference.
# Writes OUT/*.json (eval tables) and prints them. About 30 minutes on two cores.
#
#   scripts/calibration_eval.sh DATASET [OUT] [ITEMS]
#
# DATASET: a LiDAR dataset of the prototype's grid (L = 32, e.g. `tcsense dataset lidar --count
# 200 --size 64x64 --seed 101 -o DS`); its test split is evaluated.
set -euo pipefail
cd "$(dirname "$0")/.."
DS=$(realpath "$1")
OUT=${2:-calibration-eval}
ITEMS=${3:-16}
cargo build --release --locked -q
T=$(realpath target/release/tcsense)
ZOO=$(realpath zoo/admm-lidar-delay)
mkdir -p "$OUT" && cd "$OUT"
cp "$ZOO/codes.json" codes.json
SIZE=$(python3 -c 'import json,sys; s=json.load(open(sys.argv[1]))["size"]; print(f"{s[0]}x{s[1]}")' "$DS/manifest.json")
NI=(--tap-gain 0.05 --prnu 0.02 --dark 0.01 --dark-fpn 0.002 --tail 0.25 --tail-tau-ns 2 --sensor-seed 7)
S=(--codes codes.json --irf physical)
"$T" simulate "${S[@]}" --sweep sweep --size "$SIZE" --noise --average 64 --seed 1 "${NI[@]}"
"$T" calibrate "${S[@]}" --sweep sweep -o cal
"$T" simulate "${S[@]}" --sweep clean-sweep --size "$SIZE" --average 1 "${NI[@]}"
"$T" calibrate "${S[@]}" --sweep clean-sweep -o oracle --no-report
# 10 minutes of fine-tuning the zoo decoder to the calibrated sensor (interrupted at the budget)
if [ ! -f tuned/model.bpk ]; then
  timeout -s INT 600 "$T" train admm-net --dataset "$DS" --codes codes.json --calibration cal --prior delay --channels 2 \
    --epochs 36 --batch-size 8 --lr 5e-4 --crop 32x32 --seed 4 --init-from zoo:admm-lidar-delay -o tuned || true
fi
E=(eval "${S[@]}" --noise --seed 5 --dataset "$DS" --split test --items "$ITEMS" --decoder tval3 admm-net:zoo:admm-lidar-delay)
"$T" "${E[@]}" -o ideal.json
"$T" "${E[@]}" "${NI[@]}" -o nominal.json
"$T" "${E[@]}" "${NI[@]}" --calibration cal --decoder admm-net:tuned -o calibrated.json
"$T" "${E[@]}" "${NI[@]}" --calibration oracle -o oracle.json
