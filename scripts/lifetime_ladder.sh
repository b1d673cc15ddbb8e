#!/usr/bin/env bash
# The FLIm photon ladder (issue 52): every lifetime decoder at four light levels on the FLIm sets of
# scripts/ood.sh (scripts/ood_sets.sh), through the codes of one zoo entry; one table of lifetime
# MAE (ns) · share of the fluorophore pixels with a lifetime.
#
#   scripts/lifetime_ladder.sh [OUT] [--decoder NAME …]
#
# Defaults: the fit to the taps (3×3, and pooled by likeness over 15×15), zoo:lifetime-flim-pooled, zoo:lifetime-flim-pooled-fast, zoo:lifetime-flim-pooled-wide,
# zoo:lifetime-flim-evidence-fast, zoo:lifetime-flim-evidence and zoo:lifetime-flim-designed through
# the designed codes. SIZE (64x64), ITEMS (8), LIGHT (0.8,0.1,0.02,0.005) and SBR (none) come from
# the environment.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-lifetime-ladder}
shift || true
SIZE=${SIZE:-64x64}
ITEMS=${ITEMS:-8}
LIGHT=${LIGHT:-0.8,0.1,0.02,0.005}
CODES=${CODES:-zoo/lifetime-flim-designed/codes.json}
cargo build --release --locked
B=target/release/tcsense
. scripts/ood_sets.sh
mkdir -p "$OUT"
flim_test_sets "$OUT/" 80 >/dev/null
decoders=("$@")
[ ${#decoders[@]} -eq 0 ] && decoders=(--decoder lifetime-fit --decoder lifetime-fit-pooled --decoder zoo:lifetime-flim-pooled --decoder zoo:lifetime-flim-pooled-fast --decoder zoo:lifetime-flim-pooled-wide --decoder zoo:lifetime-flim-evidence-fast --decoder zoo:lifetime-flim-evidence --decoder zoo:lifetime-flim-designed)
sbr=()
[ -n "${SBR:-}" ] && sbr=(--sbr "$SBR")
for s in standard onset-0ns onset-30ns irf-1.5ns long-lifetimes background; do
  $B eval --dataset "$OUT/$s" --items "$ITEMS" --codes "$CODES" --heterodyne 8 --irf physical --seed 5 --light "$LIGHT" "${sbr[@]}" \
    "${decoders[@]}" -o "$OUT/ladder-$s.json" >/dev/null
done
python3 - "$OUT" <<'PY'
import json, sys, glob, os
out = sys.argv[1]
rows, levels = {}, []
for f in sorted(glob.glob(f"{out}/ladder-*.json")):
    s = os.path.basename(f)[len("ladder-"):-5]
    for r in json.load(open(f)):
        l = r["light"]["signal_fraction"]
        levels += [l] if l not in levels else []
        rows.setdefault((s, r["decoder"]), {})[l] = r
print("| set | decoder | " + " | ".join(str(l) for l in levels) + " |")
print("|---|---|" + "---|" * len(levels))
for (s, d), v in rows.items():
    cell = lambda r: "–" if r is None or r["lifetime_mae_s"] is None else f"{r['lifetime_mae_s'] * 1e9:.3f} · {r['lifetime_coverage'] * 100:.0f} %"
    print(f"| {s} | {d} | " + " | ".join(cell(v.get(l)) for l in levels) + " |")
PY
