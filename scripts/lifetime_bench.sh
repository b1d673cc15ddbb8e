#!/usr/bin/env bash
# Lifetime benchmark (issue 27): every decoder on the same noisy measurements of FLIm sets that
# each differ from the paper's generator in one thing, plus the randomised test split:
# lifetime MAE of the mean lifetime over the pixels holding a fluorophore, its intensity-
# weighted value, the share within 0.2 ns and the share with a lifetime.
#
#   scripts/lifetime_bench.sh RUN [OUT] [extra --decoder flags]
#
# RUN is a `tcsense train lifetime` run on the prototype's codes (its codes and IRF are used for
# every decoder); TVAL3's cubes get the reconvolution fit. SIZE (64x64), ITEMS (8) and RANDOM (a
# randomised FLIm dataset whose test split to add) come from the environment.
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=$1
OUT=${2:-lifetime-bench}
shift 2 || shift $#
SIZE=${SIZE:-64x64}
ITEMS=${ITEMS:-8}
cargo build --release --locked
B=target/release/tcsense
. scripts/ood_sets.sh
mkdir -p "$OUT"
flim_test_sets "$OUT/" 80
irf=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['irf']['kind'])" "$RUN/config.json") # ideal or physical (the eval defaults' laser and tap)
echo "set,decoder,items,mse,psnr_db,b1r,b1m,b1d,b2r,b2m,b2d,lifetime_mae_s,seconds_per_frame,lifetime_mae_weighted_s,lifetime_within_02ns,lifetime_coverage" > "$OUT/lifetime.csv"
evaluate() { # NAME DATASET [extra eval flags]
  local name=$1 ds=$2
  shift 2
  $B eval --dataset "$ds" --split test --items "$ITEMS" --codes "$RUN/codes.json" --heterodyne 8 --irf "$irf" --noise --seed 5 \
    --decoder tval3 --decoder "lifetime:$RUN" "$@" -o "$OUT/eval-$name.json" | tail -n 3
  tail -n +2 "$OUT/eval-$name.csv" | sed "s|^|$name,|" >> "$OUT/lifetime.csv"
}
[ -n "${RANDOM_SET:-}" ] && evaluate random "$RANDOM_SET" "$@"
for s in standard onset-0ns onset-30ns irf-1.5ns long-lifetimes background; do evaluate "$s" "$OUT/$s" "$@"; done
evaluate dim-x0.1 "$OUT/standard" --brightness 0.1 "$@"
evaluate bright-x10 "$OUT/standard" --brightness 10 "$@"
echo
python3 - "$OUT/lifetime.csv" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
print("| set | decoder | MAE (ns) | intensity-weighted (ns) | within 0.2 ns | with a lifetime | ms/frame |")
print("|---|---|---|---|---|---|---|")
f = lambda v, s=1e9, d=3: f"{float(v)*s:.{d}f}" if v else "–"
for r in rows:
    print(f"| {r['set']} | {r['decoder'].split('/')[-1]} | {f(r['lifetime_mae_s'])} | {f(r['lifetime_mae_weighted_s'])} | {f(r['lifetime_within_02ns'], 100, 1)} % | {f(r['lifetime_coverage'], 100, 1)} % | {f(r['seconds_per_frame'], 1e3, 1)} |")
PY
