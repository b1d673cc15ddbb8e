#!/usr/bin/env bash
# How far exposure codes can go under the prototype's constraints (issue 53): code sets
# designed with more search, at dim light, with a stricter alias, and with the constraints
# relaxed one by one, against the zoo's designed codes — through the model's own decoders (the
# range fit, per pixel and pooled over 3×3), which need no training, so what is measured is the
# codes. LiDAR: median first-return error on the photon ladder of the ood.sh sets and the
# Middlebury motorcycle; FLIm: the lifetime Cramér–Rao bounds of `codes analyze`.
#
#   scripts/codes_headroom.sh [OUT]      (default OUT = codes-headroom-out; about 45 minutes on 2 cores)
#
# Writes OUT/CODES.json and OUT/flim-CODES.json (codes), OUT/bounds.json and OUT/flim-bounds.json
# (`codes analyze --json`), OUT/eval/CODES/SET.json (`eval --light … -o`), and prints (and writes
# to OUT/table.md) the table of docs/codes.md: per code set its alias and bounds, then per decoder and
# light level the geometric mean over the sets of its error over the designed codes' (with the
# range over the sets). From the environment: SIZE (64x64), COUNT (80 scenes per set, 8 in the
# test split), ITEMS (8), SEED (5), LIDAR_SETS (a directory holding the sets already: standard,
# far, near, textures, dense-sheet, lidar-test-motorcycle), B (a tcsense binary; default: a
# release build).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-codes-headroom-out}
SIZE=${SIZE:-64x64}
COUNT=${COUNT:-80}
ITEMS=${ITEMS:-8}
SEED=${SEED:-5}
if [ -z "${B:-}" ]; then
  cargo build --release --locked
  B=$PWD/target/release/tcsense
fi
. scripts/ood_sets.sh
mkdir -p "$OUT"
lidar_sets_in "$OUT" "$COUNT"

SHAPE=(--taps 4 --block 2x2 --length 32 --seed 1)
ALL=(--tap-constraint --hamming 2 --window 2)
# name: the flags of `codes select` beside SHAPE (the first is the zoo's designed codes)
DESIGNS=(
  "designed ${ALL[*]}"
  "designed-dim ${ALL[*]} --photons 300 --ambient 30"
  "search-10x ${ALL[*]} --candidates 200000 --search 200000"
  "alias-0.9 ${ALL[*]} --alias-threshold 0.9"
  "tap-hamming --tap-constraint --hamming 2"
  "tap-window --tap-constraint --window 2"
  "hamming-4 --tap-constraint --hamming 4 --window 2"
  "tap --tap-constraint"
  "unconstrained-dim --photons 300 --ambient 30"
)
# design FILE SELECT_FLAGS…: `codes select` into FILE, once (written whole or not at all)
design() {
  local f=$1
  shift
  [ -f "$f" ] && return
  echo "== codes select $*"
  "$B" codes select "$@" -o "$f.tmp" > /dev/null
  mv "$f.tmp" "$f"
}

# bits_from FIRST OTHER…: how many bits each codes file is from FIRST's
bits_from() {
  python3 - "$@" <<'EOF'
import json, sys
# bits: per subpixel, per tap, one string of L masks
bits = {p: "".join("".join(t) for t in json.load(open(p))["bits"]) for p in sys.argv[1:]}
first = sys.argv[1]
for p in sys.argv[2:]:
    d = sum(u != v for u, v in zip(bits[first], bits[p]))
    print(f"{p}: {d} bits from {first}" if d else f"{p}: the bits of {first}")
EOF
}

NAMES=()
CODES=()
for d in "${DESIGNS[@]}"; do
  read -r name flags <<< "$d"
  NAMES+=("$name")
  CODES+=("$OUT/$name.json")
  # shellcheck disable=SC2086
  design "$OUT/$name.json" --criterion range "${SHAPE[@]}" $flags
done
bits_from zoo/unet-lidar-designed/codes.json "${CODES[@]}"

# the bounds at dim light (300 e⁻ signal, 30 e⁻ ambient), LiDAR and FLIm (heterodyne 8)
"$B" codes analyze "${CODES[@]}" --irf physical --photons 300 --ambient 30 --json > "$OUT/bounds.json"
FLIM=(
  "designed ${ALL[*]}"
  "designed-dim ${ALL[*]} --photons 300 --ambient 30"
  "search-5x ${ALL[*]} --candidates 100000 --search 200000"
  "unconstrained-dim --photons 300 --ambient 30"
)
FCODES=()
for d in "${FLIM[@]}"; do
  read -r name flags <<< "$d"
  FCODES+=("$OUT/flim-$name.json")
  # shellcheck disable=SC2086
  design "$OUT/flim-$name.json" --criterion lifetime --heterodyne 8 "${SHAPE[@]}" $flags
done
bits_from zoo/lifetime-flim-designed/codes.json "${FCODES[@]}"
"$B" codes analyze "${FCODES[@]}" --irf physical --heterodyne 8 --photons 300 --ambient 30 --json > "$OUT/flim-bounds.json"

# the ladder: every code set through the range fit, per pixel and pooled, the same items and noise
for n in "${NAMES[@]}"; do
  mkdir -p "$OUT/eval/$n"
  for s in standard far near textures dense-sheet lidar-test-motorcycle; do
    [ -f "$OUT/eval/$n/$s.json" ] && continue
    echo "== $n on $s"
    "$B" eval --dataset "$LIDAR_SETS/$s" --items "$ITEMS" --codes "$OUT/$n.json" --irf physical --seed "$SEED" \
      --light 0.8,0.1,0.02,0.005 --decoder depth-fit --decoder depth-fit-pooled -o "$OUT/eval/$n/$s.json" > /dev/null
  done
done
python3 scripts/codes_headroom.py "$OUT" "${NAMES[@]}" | tee "$OUT/table.md"
