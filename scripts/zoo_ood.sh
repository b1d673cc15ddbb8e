#!/usr/bin/env bash
# The zoo's out-of-distribution tables (issue 28): each zoo entry next to TVAL3 (and, for FLIm,
# the lifetime fit to the taps) on the same noisy measurements of test sets that each differ
# from the randomised generator in one thing — the sets of scripts/ood.sh, at the zoo's frame
# size — plus a real depth scene (Middlebury 2014 "Motorcycle", from the scikit-image wheel)
# and the entry's own data's test split when it is found (DATA_LIDAR, DATA_FLIM).
#
#   scripts/zoo_ood.sh [OUT] [NAME ...]     (default OUT = zoo-ood-out, every entry)
#
# Every entry is decoded with its own codes and IRF (zoo/NAME/config.json). SIZE (64x64) and
# ITEMS (10 test items per set) come from the environment; TVAL3=0 leaves TVAL3 out (the FLIm
# sets take about 20 minutes of it per entry). Results: OUT/zoo-ood.csv and a
# Markdown table per entry (OUT/NAME.md, also printed) for its PROVENANCE.md.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-zoo-ood-out}
shift || true
SIZE=${SIZE:-64x64}
ITEMS=${ITEMS:-10}
cargo build --release --locked
B=$PWD/target/release/tcsense
. scripts/ood_sets.sh
mkdir -p "$OUT"
if [ $# -gt 0 ]; then NAMES=("$@"); else mapfile -t NAMES < <(find zoo -mindepth 2 -maxdepth 2 -name config.json -not -path 'zoo/drafts/*' | sed 's|zoo/||; s|/config.json||' | sort); fi
field() { python3 -c "import json,sys; c=json.load(open(sys.argv[1])); print(eval(sys.argv[2]))" "zoo/$1/config.json" "$2"; }

lidar_sets() {
  [ -f "$OUT/.lidar-sets" ] && return
  lidar_test_sets "$OUT/lidar-test-" 120
  motorcycle_set "$OUT"
  touch "$OUT/.lidar-sets"
}

flim_sets() {
  [ -f "$OUT/.flim-sets" ] && return
  flim_test_sets "$OUT/flim-test-" 120
  touch "$OUT/.flim-sets"
}

[ -f "$OUT/zoo-ood.csv" ] || echo "entry,set,decoder,items,mse,psnr_db,bounce1_rmse_m,bounce1_mae_m,bounce1_detection,bounce2_rmse_m,bounce2_mae_m,bounce2_detection,lifetime_mae_s,seconds_per_frame,lifetime_mae_weighted_s,lifetime_within_02ns,lifetime_coverage,bounce1_false_alarm,bounce2_false_alarm,bounce1_median_m,bounce2_median_m" > "$OUT/zoo-ood.csv"
for name in "${NAMES[@]}"; do
  kind=$(field "$name" "c['decoder']")
  mode=$(field "$name" "c['sampling']['mode']")
  irf=$(field "$name" "c['irf']['kind']")
  grid=""; decoders=()
  [ "${TVAL3:-1}" = 0 ] || decoders=(--decoder tval3)
  if [ "$mode" = heterodyne ]; then
    flim_sets
    grid="--heterodyne $(field "$name" "c['sampling']['k']")"
    decoders+=(--decoder lifetime-fit)
    sets=(standard onset-0ns onset-30ns irf-1.5ns long-lifetimes background)
    prefix=flim; own=${DATA_FLIM:-}
  else
    lidar_sets
    sets=(standard far near textures dense-sheet motorcycle)
    prefix=lidar; own=${DATA_LIDAR:-}
  fi
  decoders+=(--decoder "$kind:zoo:$name")
  # a U-Net's ranges are refined in the tap domain; its network's own ranges next to them
  if [ "$kind" = unet ]; then decoders+=(--decoder "unet-raw:zoo:$name"); fi
  evaluate() { # SET DATASET [extra eval flags]
    local set=$1 ds=$2
    shift 2
    echo "== zoo:$name on $set"
    $B eval --dataset "$ds" --split test --items "$ITEMS" --codes "zoo/$name/codes.json" $grid --irf "$irf" --noise --seed 5 \
      "${decoders[@]}" "$@" -o "$OUT/eval-$name-$set.json" | tail -n $(( ${#decoders[@]} / 2 + 1 )) | head -n $(( ${#decoders[@]} / 2 ))
    tail -n +2 "$OUT/eval-$name-$set.csv" | sed "s|^|$name,$set,|" >> "$OUT/zoo-ood.csv"
  }
  [ -n "$own" ] && evaluate own-test "$own"
  for s in "${sets[@]}"; do evaluate "$s" "$OUT/$prefix-test-$s"; done
  evaluate dim-x0.1 "$OUT/$prefix-test-standard" --brightness 0.1
  evaluate bright-x10 "$OUT/$prefix-test-standard" --brightness 10
  python3 - "$OUT/zoo-ood.csv" "$name" "$prefix" > "$OUT/$name.md" <<'PY'
import csv, sys
path, name, prefix = sys.argv[1:]
rows = [r for r in csv.DictReader(open(path)) if r["entry"] == name]
f = lambda v, s=1.0, d=3: "–" if v in ("", "NaN", "nan") else f"{float(v) * s:.{d}f}"
pct = lambda v: "–" if v in (None, "", "NaN", "nan") else f"{float(v) * 100:.1f} %"
label = lambda d: ("this entry, network alone" if d.startswith("unet-raw:") else "this entry") if d.endswith(f"zoo:{name}") else d
if prefix == "lidar":
    print("| set | decoder | PSNR (dB) | first-return MAE (m) | second-return MAE (m) | false second returns | ms/frame |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['set']} | {label(r['decoder'])} | {f(r['psnr_db'], 1, 2)} | {f(r['bounce1_mae_m'])} | {f(r['bounce2_mae_m'])} | {pct(r.get('bounce2_false_alarm'))} | {f(r['seconds_per_frame'], 1e3, 1)} |")
else:
    print("| set | decoder | lifetime MAE (ns) | intensity-weighted (ns) | within 0.2 ns | with a lifetime | ms/frame |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['set']} | {label(r['decoder'])} | {f(r['lifetime_mae_s'], 1e9)} | {f(r['lifetime_mae_weighted_s'], 1e9)} | {f(r['lifetime_within_02ns'], 100, 1)} % | {f(r['lifetime_coverage'], 100, 1)} % | {f(r['seconds_per_frame'], 1e3, 1)} |")
PY
  echo; cat "$OUT/$name.md"; echo
done
