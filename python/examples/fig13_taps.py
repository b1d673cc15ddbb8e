"""The paper's Fig. 13(a) from Python: TVAL3's MSE against the number of taps M (2×2 block,
L = 32), one curve per constraint setting, best of a few random code sets per point.

    python python/examples/fig13_taps.py [--out fig13a.png] [--candidates 3] [--size 32]

Scenes: randomised LiDAR transients (tcsense.generate_dataset), noise-free tap images, as in
the paper's code study. Takes about a minute on two cores at the defaults.
"""

import argparse
import pathlib
import tempfile

import numpy as np

import tcsense

SERIES = {
    "no constraint": dict(),
    "tap": dict(tap_constraint=True),
    "tap + H 2 + W 2": dict(tap_constraint=True, hamming=2, window=2),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="fig13a.png", help="PNG to write (and a .csv beside it)")
    ap.add_argument("--candidates", type=int, default=3, help="random code sets per point (the best counts)")
    ap.add_argument("--size", type=int, default=32, help="frame side in pixels")
    ap.add_argument("--items", type=int, default=3, help="test scenes scored")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with tempfile.TemporaryDirectory() as tmp:
        ds = tcsense.generate_dataset("lidar", pathlib.Path(tmp) / "lidar", 30, size=(args.size, args.size), seed=args.seed)
        x = ds.load("test", "x")[: args.items]  # [B, T, H, W]
    rows = []
    for name, constraints in SERIES.items():
        for taps in range(1, 9):
            best = np.inf
            for k in range(args.candidates):
                try:
                    codes = tcsense.Codes.generate(taps=taps, block=(2, 2), length=32, seed=args.seed + k, **constraints)
                except tcsense.TcsenseError:
                    break  # no codes meet these constraints with this many taps
                sensor = tcsense.Sensor(codes, irf="ideal")
                xh = tcsense.tval3(sensor.forward(x), sensor)
                best = min(best, float(np.mean((xh - x) ** 2)))
            if np.isfinite(best):
                rows.append((name, taps, best))
                print(f"{name:>16}  M = {taps}  MSE {best:.3e}")

    out = pathlib.Path(args.out)
    out.with_suffix(".csv").write_text("setting,taps,mse\n" + "".join(f"{n},{m},{e:.6e}\n" for n, m, e in rows))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name in SERIES:
        pts = [(m, e) for n, m, e in rows if n == name]
        if pts:
            ax.semilogy(*zip(*pts), marker="o", label=name)
    ax.set_title("TVAL3 reconstruction error against the number of taps\n(2×2 block, L = 32, noise-free; paper Fig. 13a)")
    ax.set_xlabel("taps M")
    ax.set_ylabel("MSE of the transient cube (normalised units)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(title="exposure-code constraints")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    print(f"wrote {out} and {out.with_suffix('.csv')}")


if __name__ == "__main__":
    main()
