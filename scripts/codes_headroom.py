#!/usr/bin/env python3
"""The table of scripts/codes_headroom.sh, from its output directory.

    codes_headroom.py OUT DESIGNED OTHER…      (Markdown on stdout)

Reads OUT/bounds.json and OUT/flim-bounds.json (`codes analyze --json`) and OUT/eval/NAME/SET.json
(`eval --light … -o` with the decoders depth-fit and depth-fit-pooled) and prints: per code set
its range alias and bounds; per decoder, code set and light level the geometric mean over the
sets of the first return's median error over DESIGNED's, with the smallest and largest ratio;
the FLIm lifetime bounds.
"""
import json
import math
import os
import sys


def errors(path):
    """{(decoder, signal): first-return median error (m)} of one eval ladder."""
    out = {}
    for r in json.load(open(path)):
        m = r.get("depth_median_m") or []
        if m and not math.isnan(m[0]):
            out[(r["decoder"], r["light"]["signal_fraction"])] = m[0]
    return out


def main():
    out, designed, others = sys.argv[1], sys.argv[2], sys.argv[3:]
    names = [designed] + others
    bounds = {os.path.basename(b["codes"])[:-5]: b["report"] for b in json.load(open(os.path.join(out, "bounds.json")))}
    light = next(iter(bounds.values()))["light"]
    print(f"Range bounds at {light['photons']:g} e⁻ signal, {light['ambient']:g} e⁻ ambient (bins):\n")
    print("| codes | alias | worst bound | mean bound |")
    print("|---|---|---|---|")
    for n in names:
        r = bounds[n]
        print(f"| {n} | {r['range_alias']['distance']:.3f} | {r['range']['worst_bins']:.3f} | {r['range']['mean_bins']:.3f} |")

    sets = sorted(f[:-5] for f in os.listdir(os.path.join(out, "eval", designed)) if f.endswith(".json"))
    # every ladder read once: {code set: {set: errors}}
    ladders = {
        n: {s: errors(p) for s in sets if os.path.exists(p := os.path.join(out, "eval", n, s + ".json"))} for n in names
    }
    base = ladders[designed]
    decoders = sorted({d for e in base.values() for d, _ in e})
    levels = sorted({l for e in base.values() for _, l in e}, reverse=True)
    print(f"\nFirst-return median error over {designed}'s, geometric mean over {len(sets)} sets (min–max):")
    for d in decoders:
        print(f"\n`{d}`\n")
        print("| codes | " + " | ".join(f"{l:g}" for l in levels) + " |")
        print("|---|" + "---|" * len(levels))
        for n in others:
            cells = []
            for l in levels:
                ratios = []
                for s, mine in ladders[n].items():
                    mine, theirs = mine.get((d, l)), base[s].get((d, l))
                    if mine and theirs:
                        ratios.append(mine / theirs)
                if ratios:
                    gm = math.exp(sum(map(math.log, ratios)) / len(ratios))
                    cells.append(f"{gm:.2f} ({min(ratios):.2f}–{max(ratios):.2f})")
                else:
                    cells.append("–")
            print(f"| {n} | " + " | ".join(cells) + " |")

    p = os.path.join(out, "flim-bounds.json")
    if os.path.exists(p):
        print("\nFLIm (heterodyne 8): lifetime bound with the onset known, mean over the onsets (ns):\n")
        flim = json.load(open(p))
        grid = [q["tau_s"] for q in flim[0]["report"]["lifetime"]]
        # the grid's lifetimes nearest 0.5, 1, 3 and 8 ns
        pick = sorted({min(range(len(grid)), key=lambda i: abs(math.log(grid[i] / t))) for t in (0.5e-9, 1e-9, 3e-9, 8e-9)})
        print("| codes | alias | " + " | ".join(f"τ {grid[i] * 1e9:.2f} ns" for i in pick) + " |")
        print("|---|---|" + "---|" * len(pick))
        for b in flim:
            r = b["report"]
            cells = [f"{r['lifetime'][i]['known_mean_s'] * 1e9:.4f}" for i in pick]
            print(f"| {os.path.basename(b['codes'])[:-5]} | {r['range_alias']['distance']:.3f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
