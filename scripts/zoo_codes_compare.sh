#!/usr/bin/env bash
# Learned codes against designed codes, entry by entry (issue 53): every zoo entry whose codes
# were learned with its decoder, beside the entry of the same network on the designed (or
# given) codes, on the photon ladder of the ood.sh sets (and, for LiDAR, the Middlebury
# motorcycle), each through its own codes, the same items and noise seeds. The product compared
# is what users read: the first return's median error (LiDAR), the lifetime MAE (FLIm).
#
#   scripts/zoo_codes_compare.sh [OUT]      (default OUT = zoo-codes-out; about 15 minutes on 2 cores)
#
# Writes OUT/NAME.json per learned entry (scripts/codes_comparison.py: the per-set table, the
# ratios and the verdict) and, with WRITE=1, zoo/NAME/codes_comparison.json, which `tcsense zoo
# list` and `zoo show` read: an entry whose learned codes do not meet issue 53's rule (at most
# 0.8× at signal 0.02 and 1.05× at 0.8, geometric mean over the sets) is listed as a baseline.
# From the environment: SIZE (64x64) and COUNT (80 scenes per set, 8 in the test split), ITEMS
# (8), SEED (5); LIDAR_SETS / FLIM_SETS: directories holding the sets already (standard, far,
# near, textures, dense-sheet, lidar-test-motorcycle / standard, onset-0ns, onset-30ns,
# irf-1.5ns, long-lifetimes, background); B: a tcsense binary (default: a release build).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-zoo-codes-out}
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
flim_sets_in "$OUT" "$COUNT"
LADDER=0.8,0.1,0.02,0.005

# ladder ENTRY DOMAIN: the entry on every set of its domain, through its own codes
ladder() {
  local e=$1 domain=$2 sets dir extra=()
  if [ "$domain" = lidar ]; then
    sets="standard far near textures dense-sheet lidar-test-motorcycle"; dir=$LIDAR_SETS
  else
    sets="standard onset-0ns onset-30ns irf-1.5ns long-lifetimes background"; dir=$FLIM_SETS; extra=(--heterodyne 8)
  fi
  mkdir -p "$OUT/$e"
  for s in $sets; do
    [ -f "$OUT/$e/$s.json" ] && continue
    echo "== $e on $s"
    "$B" eval --dataset "$dir/$s" --items "$ITEMS" --codes "zoo/$e/codes.json" "${extra[@]}" --irf physical --seed "$SEED" \
      --light "$LADDER" --decoder "zoo:$e" -o "$OUT/$e/$s.json" > /dev/null
  done
}

# learned entry, the same network on designed (or given) codes, domain
PAIRS=(
  "admm-lidar-learned admm-lidar-designed lidar"
  "unet-lidar-learned unet-lidar-designed lidar"
  "lifetime-flim-learned lifetime-flim-designed flim"
  "admm-flim-learned admm-flim-delay flim"
)
for p in "${PAIRS[@]}"; do
  read -r learned against domain <<< "$p"
  ladder "$learned" "$domain"
  ladder "$against" "$domain"
  python3 scripts/codes_comparison.py "$OUT" "$learned" "$against" "$domain" --items "$ITEMS" --seed "$SEED" > "$OUT/$learned.json"
  if [ "${WRITE:-0}" = 1 ]; then cp "$OUT/$learned.json" "zoo/$learned/codes_comparison.json"; fi
  python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(d['entry'], d['verdict'], 'ratios', d['ratio'])" "$OUT/$learned.json"
done
