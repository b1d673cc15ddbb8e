#!/usr/bin/env bash
# The main job, end to end on a small problem: design exposure codes under the paper's
# constraints, export them to the sensor's code memory, generate a LiDAR dataset with
# multipath, simulate the sensor's tap images (shot + read noise), reconstruct them with
# TVAL3 and turn the cube into depth maps (two returns), a point cloud and waveform plots.
# Everything lands in ./demo-out (or the directory given as the first argument).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-demo-out}
cargo build --release --locked --quiet
tc=target/release/tcsense
mkdir -p "$out"
set -x
$tc codes generate --taps 4 --block 2x2 --length 32 --tap-constraint --hamming 2 --window 2 --seed 1 -o "$out/codes.json"
$tc codes check "$out/codes.json"
$tc codes export "$out/codes.json" -o "$out/code-memory"
$tc codes show "$out/codes.json" -o "$out/codes.png"
$tc dataset lidar --count 8 --size 64x64 --sheet-probability 1 --seed 1 --force -o "$out/lidar"
$tc dataset show "$out/lidar" --split test -o "$out/lidar-test.png"
$tc sensor matrix --codes "$out/codes.json" --irf physical -o "$out/A.npy"
$tc simulate --codes "$out/codes.json" --cube "$out/lidar/test/x_000.npy" \
    --noise --full-well 20000 --read-noise 40 --seed 1 -o "$out/y.npy"
$tc reconstruct tval3 --codes "$out/codes.json" --measurements "$out/y.npy" -o "$out/xhat.npy"
$tc depth "$out/xhat.npy" --peaks 2 -o "$out/depth.npy" --ply "$out/cloud.ply" --png "$out/depth.png"
$tc eval --dataset "$out/lidar" --codes "$out/codes.json" --decoder tval3 --noise --seed 1 -o "$out/eval.json"
$tc bench forward --reps 5
