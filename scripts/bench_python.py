#!/usr/bin/env python3
"""The cost of a call through Python: forward and adjoint at the sensor's frame size through
the `tcsense` module against the same operators timed in Rust (`tcsense bench forward`),
interleaved over rounds (this machine's speed drifts by ±30 % over minutes).

    scripts/bench_python.py [--size 188x212] [--reps 20] [--rounds 3] [--bin target/release/tcsense]

Needs the package installed (`pip install ./python`) and a built binary. Prints, per round
and bins T, the median ms of: Rust `forward_into`/`adjoint_into`; Python with `out=` (the
same no-allocation call); Python returning a new array (allocates the output).
"""

import argparse
import pathlib
import re
import subprocess
import time

import numpy as np

import tcsense

REPO = pathlib.Path(__file__).resolve().parents[1]


def median_ms(f, reps):
    f()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        f()
        ts.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ts))


def rust(binary, size, reps):
    out = subprocess.run([binary, "bench", "forward", "--size", size, "--reps", str(reps)], capture_output=True, text=True, check=True).stdout
    rows = {}
    for line in out.splitlines():
        m = re.match(r"\s*(\d+)\s+(\d+)\s+([\d.]+)\s+[\d.]+\s+([\d.]+)", line)
        if m:
            rows[int(m.group(1))] = (float(m.group(3)), float(m.group(4)))
    return rows


def python(size, reps):
    h, w = map(int, size.split("x"))
    rows = {}
    for k in (1, 4):
        codes = tcsense.Codes.generate(taps=4, block=(2, 2), length=32, tap_constraint=True, hamming=2, window=2, clock_hz=607e6, seed=1)
        s = tcsense.Sensor(codes, oversample=k)
        t = s.bins
        j, r, c = np.meshgrid(np.arange(t), np.arange(h), np.arange(w), indexing="ij")
        x = ((j * 7 + r * 3 + c) % 11).astype(np.float32)
        y = np.zeros((4, h, w), dtype=np.float32)
        xa = np.zeros((t, h, w), dtype=np.float32)
        fo = median_ms(lambda: s.forward(x, out=y), reps)
        ao = median_ms(lambda: s.adjoint(y, out=xa), reps)
        fn = median_ms(lambda: s.forward(x), reps)
        an = median_ms(lambda: s.adjoint(y), reps)
        rows[t] = (fo, ao, fn, an)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="188x212")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--bin", default=str(REPO / "target" / "release" / "tcsense"))
    a = ap.parse_args()
    print(f"forward/adjoint at {a.size}, 4 taps 2x2, median of {a.reps}; ms per call")
    print(f"{'round':>5} {'T':>4} | {'Rust fwd':>9} {'Py out=':>8} {'Py new':>8} | {'Rust adj':>9} {'Py out=':>8} {'Py new':>8} | {'overhead out=':>14}")
    ratios = []
    for r in range(a.rounds):
        ru = rust(a.bin, a.size, a.reps)
        py = python(a.size, a.reps)
        for t in sorted(ru):
            rf, ra = ru[t]
            fo, ao, fn, an = py[t]
            ov = (fo + ao) / (rf + ra) - 1
            ratios.append(ov)
            print(f"{r + 1:>5} {t:>4} | {rf:>9.3f} {fo:>8.3f} {fn:>8.3f} | {ra:>9.3f} {ao:>8.3f} {an:>8.3f} | {100 * ov:>13.1f}%")
    print(f"median overhead of the Python call with out= (forward + adjoint): {100 * float(np.median(ratios)):.1f}%")


if __name__ == "__main__":
    main()
