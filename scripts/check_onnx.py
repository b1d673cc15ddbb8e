#!/usr/bin/env python3
"""Validate an exported tcsense model outside tcsense.

    scripts/check_onnx.py model.onnx [--measurements y.npy] [--sensor-matrix A.npy]
                          [--compare OUT] [--tol 1e-4]

1. `onnx.checker.check_model(full_check=True)` and strict shape inference;
2. runs the model in onnxruntime (Python) on the measurements (a frame [M, H, W] or a stack
   [F, M, H, W]; default: random tap images of a frame allowed by the model's frame rule);
3. with --compare OUT (a `tcsense infer` output directory), checks that onnxruntime-Python's
   outputs equal tcsense's (cube.npy, or depth.npy + confidence.npy) within TOL of the
   output scale.
Prints one line per check; exit status 0 when all pass, 1 otherwise.
Needs onnx, onnxruntime and numpy (scripts/setup.sh installs them into .venv).
"""
import argparse
import sys

import numpy as np
import onnx
import onnxruntime as ort


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model")
    ap.add_argument("--measurements")
    ap.add_argument("--sensor-matrix")
    ap.add_argument("--compare")
    ap.add_argument("--tol", type=float, default=1e-4)
    a = ap.parse_args()

    model = onnx.load(a.model)
    onnx.checker.check_model(model, full_check=True)
    onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True)
    meta = {p.key: p.value for p in model.metadata_props}
    inits = {i.name for i in model.graph.initializer}
    inputs = [i.name for i in model.graph.input]
    assert not inits.intersection(inputs), f"initializers listed as graph inputs: {inits.intersection(inputs)}"
    print(f"ok  checker (full) and strict shape inference: ir_version {model.ir_version}, opset "
          f"{model.opset_import[0].version}, {len(model.graph.node)} nodes, inputs {inputs}, "
          f"decoder {meta.get('decoder')}, frame multiple {meta.get('frame_multiple')}")

    m = int(meta["taps"])
    fh, fw = (int(v) for v in meta["frame_multiple"].split("x"))
    if a.measurements:
        y = np.load(a.measurements).astype(np.float32)
    else:
        y = np.random.default_rng(0).uniform(0, 1000, size=(m, 4 * fh, 4 * fw)).astype(np.float32)
    single = y.ndim == 3
    if single:
        y = y[None]
    sess = ort.InferenceSession(a.model, providers=["CPUExecutionProvider"])
    feeds = {"measurements": y}
    if "sensor_matrix" in inputs:
        if not a.sensor_matrix:
            sys.exit("this model takes the sensor matrix as an input: give --sensor-matrix A.npy")
        feeds["sensor_matrix"] = np.load(a.sensor_matrix).astype(np.float32)
    names = [o.name for o in sess.get_outputs()]
    outs = dict(zip(names, sess.run(None, feeds)))
    for n, v in outs.items():
        if n == "depth":  # a graph from the taps (export onnx --from-taps) gives NaN where no return
            assert np.isfinite(v).any() and not np.isinf(v).any(), f"output {n}: no finite range, or an infinite one"
        else:
            assert np.isfinite(v).all(), f"output {n} has non-finite values"
        print(f"ok  onnxruntime {ort.__version__}: {n} {list(v.shape)}, range [{np.nanmin(v):.4g}, {np.nanmax(v):.4g}]")

    if a.compare:
        worst = 0.0
        for n, v in outs.items():
            ref = np.load(f"{a.compare}/{n}.npy")
            v = v[0] if single else v
            if n == "depth":  # tcsense masks undetected returns with NaN
                keep = np.isfinite(ref)
                if np.isnan(v).any() and not np.array_equal(np.isnan(v), ~keep):
                    print(f"BAD {n}: NaN where tcsense infer has a range, or the reverse")
                    worst = float("inf")
                v, ref = v[keep], ref[keep]
            scale = max(float(np.abs(ref).max()), 1e-12)
            err = float(np.abs(v - ref).max()) / scale
            worst = max(worst, err)
            status = "ok " if err <= a.tol else "BAD"
            print(f"{status} {n}: max |onnxruntime-Python - tcsense infer| = {err:.2e} of the output scale (tol {a.tol:g})")
        if worst > a.tol:
            sys.exit(1)


if __name__ == "__main__":
    main()
