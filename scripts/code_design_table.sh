#!/usr/bin/env bash
# The code-design table of docs/codes.md: for the prototype's constraints (4 taps, 2x2, L = 32,
# tap + H 2 + W 2, physical IRF), TVAL3 MSE, range alias, worst and mean range bound and the
# worst lifetime bound of
#   - the zoo's prototype codes (random, seed 1), the best of 20 random sets by TVAL3 MSE
#     (the paper's selection), the best of 20 000 by the range criterion without and with the
#     local search (the default of `codes select --criterion range`), the lifetime criterion's
#     design, and the zoo's learned codes;
# plus range-bound.png and lifetime-bound.png of all of them. About 3 minutes on two cores.
#
#   scripts/code_design_table.sh [OUT]      (default target/code-design)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-target/code-design}
mkdir -p "$OUT"
cargo build --release --locked --quiet
T=$PWD/target/release/tcsense
ZOO=$PWD/zoo
cd "$OUT"
CONS=(--taps 4 --block 2x2 --length 32 --tap-constraint --hamming 2 --window 2)
[ -f ds/manifest.json ] || "$T" dataset lidar --count 40 --size 32x32 --seed 5 -o ds >/dev/null
"$T" codes generate "${CONS[@]}" --seed 1 -o prototype.json >/dev/null
"$T" codes select --criterion mse --dataset ds --irf physical --items 2 --candidates 20 "${CONS[@]}" --seed 1 -o best-mse.json >/dev/null
"$T" codes select --criterion range "${CONS[@]}" --search 0 --seed 1 -o best-range.json >/dev/null
"$T" codes select --criterion range "${CONS[@]}" --seed 1 -o designed-range.json >/dev/null
"$T" codes select --criterion lifetime --heterodyne 8 "${CONS[@]}" --seed 1 -o designed-lifetime.json >/dev/null
cp "$ZOO/admm-lidar-learned/codes.json" learned-admm.json
cp "$ZOO/unet-lidar-learned/codes.json" learned-unet.json
SETS=(prototype best-mse best-range designed-range designed-lifetime learned-admm learned-unet)
for s in "${SETS[@]}"; do
  "$T" codes analyze "$s.json" --json >"$s.lidar.json"
  "$T" codes analyze "$s.json" --heterodyne 8 --json >"$s.flim.json"
  "$T" eval --dataset ds --codes "$s.json" --irf physical --decoder tval3 --items 8 -o "$s.eval.json" >/dev/null
done
"$T" codes analyze $(for s in "${SETS[@]}"; do echo "$s.json"; done) --plot plots >/dev/null
"$T" codes analyze prototype.json best-mse.json designed-lifetime.json learned-admm.json --heterodyne 8 --plot plots-flim >/dev/null
python3 - "${SETS[@]}" <<'EOF'
import json, sys
C = 299792458.0
print("| codes | TVAL3 MSE | range alias | worst range bound (mm) | mean range bound (mm) | FLIm range alias | worst lifetime bound σ(τ)/τ |")
print("|---|---|---|---|---|---|---|")
for s in sys.argv[1:]:
    l = json.load(open(f"{s}.lidar.json"))[0]["report"]
    f = json.load(open(f"{s}.flim.json"))[0]["report"]
    e = json.load(open(f"{s}.eval.json"))
    rows = e["rows"] if isinstance(e, dict) and "rows" in e else e
    mse = rows[0]["mse"]
    mm = lambda b: b * l["bin_width_s"] * C / 2 * 1e3
    rel = max(p["known_worst_s"] / p["tau_s"] for p in f["lifetime"])
    print(f"| {s} | {mse:.3e} | {l['range_alias']['distance']:.3f} | {mm(l['range']['worst_bins']):.1f} | {mm(l['range']['mean_bins']):.1f} | {f['range_alias']['distance']:.3f} | {rel:.3f} |")
EOF
