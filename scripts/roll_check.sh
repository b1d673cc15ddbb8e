#!/usr/bin/env bash
# A real scene moved through the range: the Middlebury 2014 motorcycle (scikit-image wheel from
# PyPI, as scripts/ood.sh) with its ranges shifted by 0, 8, 16 and 24 bins (cyclically, modulo
# the unambiguous range), rendered with the sensor's pulse, measured with noise through the
# physical IRF and decoded by every LiDAR zoo entry and TVAL3 (+ peaks) on the entry's own codes.
# A code set that aliases two ranges fails at the shifts that put the scene on them.
#
#   scripts/roll_check.sh [OUT] [NAME ...]     (default OUT = target/roll-check, every LiDAR entry)
#
# Prints the first-return MAE in bins (Δ = c·T_c/2 = 0.247 m) per entry, decoder and shift, and
# writes OUT/roll.csv. ITEMS is 1 (the scene); SIZE 96x128 (the motorcycle's crop).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-target/roll-check}
shift || true
cargo build --release --locked --quiet
B=$PWD/target/release/tcsense
SIZE=96x128
. scripts/ood_sets.sh
mkdir -p "$OUT"
[ -f "$OUT/range.npy" ] || motorcycle_set "$OUT" >/dev/null
if [ $# -gt 0 ]; then NAMES=("$@"); else
  mapfile -t NAMES < <(for c in zoo/*/config.json; do python3 -c "import json,sys; c=json.load(open(sys.argv[1])); sys.exit(0 if c['sampling']['mode'] != 'heterodyne' else 1)" "$c" && basename "$(dirname "$c")"; done)
fi
SHIFTS=(0 8 16 24)
for k in "${SHIFTS[@]}"; do
  [ -f "$OUT/moto-$k/manifest.json" ] && continue
  .venv/bin/python - "$OUT" "$k" <<'EOF'
import numpy as np, sys
out, k = sys.argv[1], int(sys.argv[2])
delta = 299792458.0 / 607e6 / 2          # metres per bin (K = 1)
cycle = 32 * delta
r = np.load(f"{out}/range.npy")
s = np.where(r > 0, np.mod(r + k * delta, cycle), 0.0).astype(np.float32)
np.save(f"{out}/range-{k}.npy", s)
EOF
  $B dataset import --depth "$OUT/range-$k.npy" --albedo "$OUT/albedo.npy" --force -o "$OUT/moto-$k" >/dev/null
done
echo "entry,decoder,shift_bins,first_return_mae_bins" > "$OUT/roll.csv"
for name in "${NAMES[@]}"; do
  kind=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['decoder'])" "zoo/$name/config.json")
  for k in "${SHIFTS[@]}"; do
    $B eval --dataset "$OUT/moto-$k" --split test --items 1 --codes "zoo/$name/codes.json" --irf physical --noise --seed 5 \
      --decoder tval3 --decoder "$kind:zoo:$name" -o "$OUT/eval-$name-$k.json" >/dev/null
    python3 - "$OUT/eval-$name-$k.csv" "$name" "$k" >> "$OUT/roll.csv" <<'EOF'
import csv, sys
delta = 299792458.0 / 607e6 / 2
path, name, k = sys.argv[1:]
for r in csv.DictReader(open(path)):
    v = r["bounce1_mae_m"]
    print(f"{name},{r['decoder']},{k},{float(v) / delta if v not in ('', 'NaN', 'nan') else float('nan'):.3f}")
EOF
  done
done
python3 - "$OUT/roll.csv" <<'EOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
shifts = sorted({int(r["shift_bins"]) for r in rows})
print("| entry | decoder | " + " | ".join(f"shift {s}" for s in shifts) + " |")
print("|---|---|" + "---|" * len(shifts))
keys = []
for r in rows:
    if (r["entry"], r["decoder"]) not in keys:
        keys.append((r["entry"], r["decoder"]))
for e, d in keys:
    vals = {int(r["shift_bins"]): r["first_return_mae_bins"] for r in rows if r["entry"] == e and r["decoder"] == d}
    print(f"| {e} | {'TVAL3 + peaks' if d == 'tval3' else 'this entry'} | " + " | ".join(vals.get(s, "–") for s in shifts) + " |")
EOF
