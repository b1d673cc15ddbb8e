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
# Writes OUT/CODES.json (codes), OUT/eval/CODES/SET.json (`eval --light … -o`), OUT/bounds.txt and
# prints the table of docs/codes.md: per code set its alias and bounds, then per decoder and
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
NAMES=()
for d in "${DESIGNS[@]}"; do
  read -r name flags <<< "$d"
  NAMES+=("$name")
  if [ ! -f "$OUT/$name.json" ]; then
    echo "== codes select: $name"
    # shellcheck disable=SC2086
    "$B" codes select --criterion range "${SHAPE[@]}" $flags -o "$OUT/$name.json.tmp" > /dev/null
    mv "$OUT/$name.json.tmp" "$OUT/$name.json"
  fi
done
if cmp -s "$OUT/designed.json" zoo/unet-lidar-designed/codes.json; then
  echo "designed.json is the zoo's designed codes (zoo/unet-lidar-designed/codes.json), byte for byte"
fi
# bits_from DIR FIRST OTHER…: how many bits each code set is from FIRST's
bits_from() {
  python3 - "$@" <<'EOF'
import json, sys
# bits: per subpixel, per tap, one string of L masks
bits = {n: "".join("".join(t) for t in json.load(open(f"{sys.argv[1]}/{n}.json"))["bits"]) for n in sys.argv[2:]}
for n in sys.argv[3:]:
    d = sum(u != v for u, v in zip(bits[sys.argv[2]], bits[n]))
    print(f"{n}: {d} bits from {sys.argv[2]}" if d else f"{n}: the bits of {sys.argv[2]}")
EOF
}
bits_from "$OUT" "${NAMES[@]}"

# the bounds at dim light (300 e⁻ signal, 30 e⁻ ambient), LiDAR and FLIm (heterodyne 8)
CODES=()
for n in "${NAMES[@]}"; do CODES+=("$OUT/$n.json"); done
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
  f=$OUT/flim-$name.json
  FCODES+=("$f")
  if [ ! -f "$f" ]; then
    echo "== codes select --criterion lifetime: $name"
    # shellcheck disable=SC2086
    "$B" codes select --criterion lifetime --heterodyne 8 "${SHAPE[@]}" $flags -o "$f.tmp" > /dev/null
    mv "$f.tmp" "$f"
  fi
done
bits_from "$OUT" flim-designed flim-designed-dim flim-search-5x flim-unconstrained-dim
cp zoo/lifetime-flim-designed/codes.json "$OUT/flim-zoo.json"
bits_from "$OUT" flim-zoo flim-designed
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
.venv/bin/python scripts/codes_headroom.py "$OUT" "${NAMES[@]}" | tee "$OUT/table.md"
