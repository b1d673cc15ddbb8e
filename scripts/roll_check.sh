#!/usr/bin/env bash
# A real scene moved through the range: the Middlebury 2014 motorcycle (scikit-image wheel from
# PyPI, as scripts/ood.sh) rendered with the sensor's pulse, its cube rolled by 0, 8, 16 and 24
# bins (the codes loop, so this is the scene k bins later on the cycle), measured with noise
# through the physical IRF and decoded by every LiDAR zoo entry and TVAL3 (+ peaks) on the
# entry's own codes.
# A code set that aliases two ranges fails at the shifts that put the scene on them.
#
#   scripts/roll_check.sh [OUT] [NAME ...]     (default OUT = target/roll-check, every LiDAR entry)
#
# Prints the median and mean first-return error in bins (Δ = c·T_c/2 = 0.247 m; the distance on
# the cycle) per entry, decoder and shift, and writes OUT/roll.csv. The scene is 96x128.
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
[ -f "$OUT/moto/manifest.json" ] || $B dataset import --depth "$OUT/range.npy" --albedo "$OUT/albedo.npy" --force -o "$OUT/moto" >/dev/null
# the cube rolled by k bins (the codes loop: the scene k bins later on the cycle), its truth with it
.venv/bin/python - "$OUT" "${SHIFTS[@]}" <<'EOF'
import numpy as np, sys
out, shifts = sys.argv[1], [int(k) for k in sys.argv[2:]]
delta = 299792458.0 / 607e6 / 2          # metres per bin (K = 1)
x = np.load(f"{out}/moto/test/x_000.npy")
d = np.load(f"{out}/moto/test/depth_000.npy")
t = x.shape[-3]
for k in shifts:
    np.save(f"{out}/x-{k}.npy", np.roll(x, k, axis=-3))
    np.save(f"{out}/depth-{k}.npy", np.where(np.isfinite(d), np.mod(d + k * delta, t * delta), np.nan).astype(np.float32))
EOF
# every entry and TVAL3 on the same noisy taps of its codes; errors on the cycle (the codes loop,
# so a surface at 0.1 bins read at 31.9 is 0.2 bins off): median and mean over the scene
echo "entry,decoder,shift_bins,median_bins,mae_bins,pixels" > "$OUT/roll.csv"
for name in "${NAMES[@]}"; do
  kind=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['decoder'])" "zoo/$name/config.json")
  codes=zoo/$name/codes.json
  for k in "${SHIFTS[@]}"; do
    d=$OUT/$name-$k
    mkdir -p "$d"
    $B simulate --codes "$codes" --irf physical --cube "$OUT/x-$k.npy" --noise --seed 5 -o "$d/y.npy" >/dev/null
    $B reconstruct tval3 --codes "$codes" --irf physical --measurements "$d/y.npy" -o "$d/tval3-x.npy" >/dev/null
    $B depth "$d/tval3-x.npy" -o "$d/tval3.npy" >/dev/null
    if [ "$kind" = unet ]; then
      $B reconstruct unet --run "zoo:$name" --measurements "$d/y.npy" -o "$d/entry.npy" >/dev/null
    else
      $B reconstruct "$kind" --run "zoo:$name" --measurements "$d/y.npy" -o "$d/entry-x.npy" >/dev/null
      $B depth "$d/entry-x.npy" -o "$d/entry.npy" >/dev/null
    fi
    .venv/bin/python - "$OUT/depth-$k.npy" "$d" "$name" "$k" >> "$OUT/roll.csv" <<'EOF'
import numpy as np, sys
truth_path, d, name, k = sys.argv[1:]
delta = 299792458.0 / 607e6 / 2
cycle = 32
t = np.load(truth_path)
t = t[0, 0] if t.ndim == 4 else t[0]
for dec in ["tval3", "entry"]:
    e = np.load(f"{d}/{dec}.npy")
    e = e[0, 0] if e.ndim == 4 else e[0]
    ok = np.isfinite(t) & np.isfinite(e) & (t > 0)
    err = np.abs(e[ok] - t[ok]) / delta % cycle
    err = np.minimum(err, cycle - err)
    print(f"{name},{dec},{k},{np.median(err):.3f},{err.mean():.3f},{ok.sum()}")
EOF
  done
done
python3 - "$OUT/roll.csv" <<'EOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
shifts = sorted({int(r["shift_bins"]) for r in rows})
print("median (mean) first-return error in bins, on the cycle")
print("| entry | decoder | " + " | ".join(f"shift {s}" for s in shifts) + " |")
print("|---|---|" + "---|" * len(shifts))
keys = []
for r in rows:
    if (r["entry"], r["decoder"]) not in keys:
        keys.append((r["entry"], r["decoder"]))
for e, d in keys:
    vals = {int(r["shift_bins"]): f"{r['median_bins']} ({r['mae_bins']})" for r in rows if r["entry"] == e and r["decoder"] == d}
    print(f"| {e} | {'TVAL3 + peaks' if d == 'tval3' else 'this entry'} | " + " | ".join(vals.get(s, "–") for s in shifts) + " |")
EOF
