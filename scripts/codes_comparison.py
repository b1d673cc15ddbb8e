#!/usr/bin/env python3
"""Learned codes against designed codes from the ladders of scripts/zoo_codes_compare.sh.

    codes_comparison.py OUT LEARNED AGAINST lidar|flim [--items N] [--seed S]  > comparison.json

Reads OUT/LEARNED/*.json and OUT/AGAINST/*.json (`tcsense eval --light … -o`, one per set) and
prints the comparison `zoo list` and `zoo show` read: per set and light level the product of
both entries (LiDAR: the first return's median error in m; FLIm: the lifetime MAE in s), the
ratio learned / against per level as the geometric mean over the sets, and the verdict: `wins`
where the ratio is at most 0.8 at signal 0.02 and at most 1.05 at 0.8 (issue 53's goal),
`on-par` where it is at most 1.05 at both (no worse, short of the goal), else `baseline` (the
learned codes lose).
"""
import argparse
import json
import math
import os
import sys

GOAL = {"0.02": 0.8, "0.8": 1.05}
NO_WORSE = {"0.02": 1.05, "0.8": 1.05}


def product(row, domain):
    if domain == "lidar":
        m = row.get("depth_median_m") or []
        return m[0] if m else None
    return row.get("lifetime_mae_s")


def ladder(path, domain):
    rows = json.load(open(path))
    return {repr(r["light"]["signal_fraction"]): product(r, domain) for r in rows}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("learned")
    ap.add_argument("against")
    ap.add_argument("domain", choices=["lidar", "flim"])
    ap.add_argument("--items", type=int, default=8)
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    sets = sorted(f[:-5] for f in os.listdir(os.path.join(a.out, a.learned)) if f.endswith(".json"))
    if not sets:
        sys.exit(f"{a.out}/{a.learned}: no ladders")
    table, levels = {}, None
    for s in sets:
        mine = ladder(os.path.join(a.out, a.learned, s + ".json"), a.domain)
        theirs = ladder(os.path.join(a.out, a.against, s + ".json"), a.domain)
        levels = levels or list(mine)
        table[s] = {"learned": [mine[l] for l in levels], "against": [theirs[l] for l in levels]}
    ratio = []
    for i, _ in enumerate(levels):
        logs = [math.log(t["learned"][i] / t["against"][i]) for t in table.values() if t["learned"][i] and t["against"][i]]
        ratio.append(round(math.exp(sum(logs) / len(logs)), 3) if logs else None)
    def meets(rule):
        return all(l in levels and ratio[levels.index(l)] is not None and ratio[levels.index(l)] <= r for l, r in rule.items())

    verdict = "wins" if meets(GOAL) else "on-par" if meets(NO_WORSE) else "baseline"
    json.dump(
        {
            "entry": a.learned,
            "against": a.against,
            "product": "first-return median error (m)" if a.domain == "lidar" else "lifetime MAE (s)",
            "levels": [float(l) for l in levels],
            "sets": table,
            "ratio": ratio,
            "verdict": verdict,
            "rule": "learned / against, the geometric mean over the sets: wins at most 0.8 at signal 0.02 and 1.05 at 0.8 (issue 53's goal); on-par at most 1.05 at both; baseline otherwise (the learned codes lose)",
            "measured": {"script": "scripts/zoo_codes_compare.sh", "items": a.items, "seed": a.seed, "irf": "physical", "noise": "on"},
        },
        sys.stdout,
        indent=1,
    )
    print()


if __name__ == "__main__":
    main()
