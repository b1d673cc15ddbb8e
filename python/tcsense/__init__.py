"""tcsense from Python: time-compressive CMOS image sensors (multitap charge modulators).

numpy float32 arrays in and out, in the axis order of the toolkit:

- transient cube ``x``: ``[T, H, W]`` (or a batch ``[B, T, H, W]``), T time bins of one cycle
- tap images ``y``: ``[M, H, W]`` (or ``[B, M, H, W]``), one image per tap
- measurement matrix ``A``: ``[N, M, T]``, N = bh·bw subpixels of the code block

The same crates as the ``tcsense`` command line do the work; errors are
:class:`TcsenseError` with the command line's message. Long calls release the GIL and
stop on Ctrl-C (``KeyboardInterrupt``).

>>> import numpy as np, tcsense
>>> codes = tcsense.Codes.generate(taps=4, block=(2, 2), length=32, tap_constraint=True,
...                                hamming=2, window=2, seed=1)
>>> sensor = tcsense.Sensor(codes, irf="physical")
>>> x = np.random.default_rng(0).random((32, 8, 8), dtype=np.float32)
>>> sensor.forward(x).shape
(4, 8, 8)
"""

import os as _os
import importlib.util as _importlib_util


def _find_onnxruntime() -> None:
    """Point the runtime at the ``onnxruntime`` wheel's library unless ORT_DYLIB_PATH is set."""
    if _os.environ.get("ORT_DYLIB_PATH"):
        return
    spec = _importlib_util.find_spec("onnxruntime")
    if spec is None or not spec.submodule_search_locations:
        return
    for root in spec.submodule_search_locations:
        lib = _os.path.join(root, "capi", "libonnxruntime.so.1.31.1")
        if _os.path.isfile(lib):
            _os.environ["ORT_DYLIB_PATH"] = lib
            return


_find_onnxruntime()

from ._tcsense import (  # noqa: E402
    DEFAULT_CLOCK_HZ,
    Codes,
    Dataset,
    Decoder,
    OnnxModel,
    Sensor,
    TcsenseError,
    bringup,
    calibrate,
    depth_map,
    export_onnx,
    find_peaks,
    fine_tune,
    fit_lifetimes,
    generate_dataset,
    lifetime_fit,
    onnxruntime_version,
    open_decoder,
    open_run,
    phasors,
    point_cloud,
    run_demo,
    simulate_sweep,
    train,
    tval3,
    write_ply,
    zoo_list,
)

__version__ = "0.1.0"

__all__ = [
    "DEFAULT_CLOCK_HZ",
    "Codes",
    "Dataset",
    "Decoder",
    "OnnxModel",
    "Sensor",
    "TcsenseError",
    "bringup",
    "calibrate",
    "depth_map",
    "export_onnx",
    "fine_tune",
    "find_peaks",
    "fit_lifetimes",
    "generate_dataset",
    "lifetime_fit",
    "onnxruntime_version",
    "open_decoder",
    "open_run",
    "phasors",
    "point_cloud",
    "run_demo",
    "simulate_sweep",
    "train",
    "tval3",
    "write_ply",
    "zoo_list",
]
