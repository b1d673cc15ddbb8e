#!/usr/bin/env python3
"""Time onnxruntime-Python on an exported tcsense model, for the side-by-side ratio with
`tcsense bench infer` (same model, same frame size, same thread count).

    tcsense bench infer --decoder unet --save-model unet.onnx
    scripts/bench_onnx.py unet.onnx [--size 188x212] [--threads 2] [--reps 7]

Prints the median time per frame (batch 1) and frames/s. Needs onnxruntime and numpy
(scripts/setup.sh installs them into .venv).
"""
import argparse
import time

import numpy as np
import onnx
import onnxruntime as ort


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model")
    ap.add_argument("--size", default="188x212")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args()
    h, w = (int(v) for v in a.size.split("x"))
    meta = {p.key: p.value for p in onnx.load(a.model, load_external_data=False).metadata_props}
    so = ort.SessionOptions()
    so.intra_op_num_threads = a.threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    sess = ort.InferenceSession(a.model, so, providers=["CPUExecutionProvider"])
    y = np.random.default_rng(1).integers(0, 4096, size=(1, int(meta["taps"]), h, w)).astype(np.float32)
    feeds = {"measurements": y}
    sess.run(None, feeds)
    times = []
    for _ in range(max(a.reps, 1)):
        t0 = time.perf_counter()
        sess.run(None, feeds)
        times.append((time.perf_counter() - t0) * 1e3)
    ms = float(np.median(times))
    print(f"onnxruntime-Python {ort.__version__}, {meta['decoder']} at {h}x{w}, {a.threads} threads: "
          f"{ms:.2f} ms/frame, {1e3 / ms:.1f} frames/s (median of {len(times)})")


if __name__ == "__main__":
    main()
