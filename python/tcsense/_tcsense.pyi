"""Type stubs of tcsense's compiled module.

Axis order everywhere: cube ``x [T, H, W]`` (T bins of one cycle), tap images ``y [M, H, W]``
(M taps), matrix ``A [N, M, T]`` (N = bh·bw subpixels); a leading batch axis ``B`` is taken
and kept. Arrays are float32. Times are in seconds, ranges in metres.
"""

import os
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
PathLike = Union[str, os.PathLike]

DEFAULT_CLOCK_HZ: float
"""The prototype's code clock, 607 MHz."""

class TcsenseError(Exception):
    """Bad input (shape, values, a file's contents, mismatched codes) or a failed step; the
    message is the command line's."""

class Codes:
    """Exposure codes: N = bh·bw subpixels × M taps × L masks per cycle, with the hardware
    constraints they were designed under (tap, Hamming H, window W)."""

    @staticmethod
    def generate(taps: int = 4, block: Tuple[int, int] = (2, 2), length: int = 32, *, tap_constraint: bool = False, hamming: Optional[int] = None, window: Optional[int] = None, drain: bool = False, clock_hz: float = ..., seed: int = 0) -> "Codes":
        """Random codes under the constraints (``tcsense codes generate``); same seed, same codes."""
    @staticmethod
    def from_bits(bits: npt.ArrayLike, block: Tuple[int, int] = (2, 2), *, tap_constraint: bool = False, hamming: Optional[int] = None, window: Optional[int] = None, drain: bool = False, clock_hz: float = ...) -> "Codes":
        """Codes from 0/1 bits ``[N, M, L]``; constraints recorded, not enforced (see ``violations``)."""
    @staticmethod
    def project(logits: F32, block: Tuple[int, int] = (2, 2), *, tap_constraint: bool = False, hamming: Optional[int] = None, window: Optional[int] = None, drain: bool = False, clock_hz: float = ...) -> "Codes":
        """Exact projection of logits ``[N, C, L]`` (C = M, or M + 1 with a drain under the tap
        constraint) onto the constraints: the feasible codes of the highest total logit."""
    @staticmethod
    def load(path: PathLike) -> "Codes":
        """Read a codes JSON file (checked against its constraints)."""
    @staticmethod
    def from_json(text: str) -> "Codes": ...
    @staticmethod
    def from_code_memory(dir: PathLike) -> "Codes":
        """Read the sensor's code memory back (``tcsense codes import``)."""
    def save(self, path: PathLike) -> None: ...
    def to_json(self) -> str: ...
    def to_code_memory(self, dir: PathLike) -> Dict[str, Any]:
        """Write chCC.bin, codes.bin and registers.json; returns the registers (ECLEN = L/8 − 1, …)."""
    def violations(self) -> List[Dict[str, Any]]:
        """The broken constraints as ``{kind, mask, subpixel, channel, detail}``; empty when feasible."""
    @property
    def feasible(self) -> bool: ...
    @property
    def bits(self) -> npt.NDArray[np.uint8]:
        """``[N, M, L]``."""
    @property
    def taps(self) -> int: ...
    @property
    def subpixels(self) -> int: ...
    @property
    def length(self) -> int: ...
    @property
    def block(self) -> Tuple[int, int]: ...
    @property
    def drain(self) -> bool: ...
    @property
    def clock_hz(self) -> float: ...
    @property
    def constraints(self) -> Dict[str, Any]:
        """``{tap, hamming, window}``."""
    @property
    def digest(self) -> str:
        """What sidecars, runs and exported models record of these codes."""

class Sensor:
    """The measurement model y = A x of a code set, as a decoder knows the sensor."""

    def __init__(self, codes: Union[Codes, PathLike], irf: Union[str, PathLike, F32, None] = None, *, oversample: Optional[int] = None, heterodyne: Optional[int] = None, laser_fwhm_ns: float = 2.55, tap_tau_ns: float = 0.3, calibration: Optional[PathLike] = None) -> None:
        """``irf``: "ideal" (default), "physical" (laser pulse ⋆ tap response) or a measured
        ``A [N, M, T]`` (array or .npy); ``oversample`` or ``heterodyne`` K gives T = L·K bins;
        ``calibration``: a ``tcsense calibrate`` directory (its measured A replaces the nominal
        one; ``correct`` applies its dark and gain maps)."""
    def forward(self, x: F32) -> F32:
        """y = A x: ``[T, H, W]`` → ``[M, H, W]`` (or batched); H, W multiples of the block."""
    def adjoint(self, y: F32) -> F32:
        """x = Aᵀ y: ``[M, H, W]`` → ``[T, H, W]`` (or batched)."""
    def measure(self, x: F32, noise: bool = True, seed: int = 0, *, full_well: float = 20000.0, read_noise: float = 40.0, signal_fraction: float = 0.8, adc_bits: int = 12, electrons_per_unit: Optional[float] = None, units: str = "input", nonideal: Optional[Dict[str, float]] = None) -> F32:
        """What the sensor reads out (``tcsense simulate``): A x with shot and read noise (e⁻),
        full-well clipping and ADC quantisation, seeded. ``nonideal``: tap_gain, prnu, dark,
        dark_fpn (fractions), crosstalk, tail, tail_tau_s, shift_s, gate_skew_s (s), modulation_contrast, nonlinearity, seed. ``units``: "input"
        (units of A x), "electrons" or "adc". ``[T, H, W]`` → ``[M, H, W]`` (or batched)."""
    def correct(self, y: F32) -> F32:
        """(y − d) / G of a calibrated sensor's raw tap images ``[M, H, W]`` (or batched)."""
    def save_measurements(self, path: PathLike, y: F32, *, noise: Optional[Dict[str, float]] = None, seed: Optional[int] = None, units: str = "input") -> None:
        """Write y (.npy) and its sidecar NAME.meta.json naming this sensor."""
    def load_measurements(self, path: PathLike) -> F32:
        """Read tap images, checked against their sidecar (codes, sampling, matrix, units)."""
    def matrix(self) -> F32:
        """``A [N, M, T]`` it decodes with (the calibration's when calibrated)."""
    def nominal_matrix(self) -> F32:
        """The nominal ``A [N, M, T]``."""
    @property
    def codes(self) -> Codes: ...
    @property
    def taps(self) -> int: ...
    @property
    def bins(self) -> int: ...
    @property
    def subpixels(self) -> int: ...
    @property
    def block(self) -> Tuple[int, int]: ...
    @property
    def bin_width_s(self) -> float: ...
    @property
    def cycle_s(self) -> float: ...
    @property
    def sampling(self) -> Tuple[str, int]:
        """("oversample" | "heterodyne", K)."""
    @property
    def irf(self) -> str: ...
    @property
    def calibration(self) -> Optional[Dict[str, Any]]:
        """calibration.json of a calibrated sensor."""

class Decoder:
    """Tap images in; cubes, depth or lifetimes out. From ``open_run`` or ``open_decoder``."""

    def decode(self, y: F32, sensor: Optional[Sensor] = None, *, clip_level: Optional[float] = None) -> Dict[str, F32]:
        """Decode ``y [M, H, W]`` (or ``[B, M, H, W]``) taken by ``sensor`` (default: the
        decoder's own). Gives the keys the decoder has: ``cube [T, H, W]``; ``depth`` (m, NaN
        where no return) and ``confidence [K, H, W]``; ``lifetime [4, H, W]`` (τ_m, τ₁, τ₂ in s,
        α₁), ``confidence`` and ``intensity [1, H, W]``. With ``clip_level`` (what a tap clipped
        at the full well reads), the pixels with a tap at it get no range and no lifetime. GIL
        released; Ctrl-C stops it."""
    @property
    def kind(self) -> str:
        """tval3, lifetime-fit, admm-net, unet, lifetime or onnx."""
    @property
    def label(self) -> str: ...
    @property
    def codes(self) -> Optional[Codes]: ...
    @property
    def sensor(self) -> Optional[Sensor]: ...
    @property
    def run(self) -> Optional[str]: ...

def open_run(run: PathLike, *, calibration: Optional[PathLike] = None) -> Decoder:
    """A trained run directory or ``zoo:NAME`` as a decoder with its codes and sensor."""

def open_decoder(name: str, *, onset_ns: Optional[float] = None, **tval3: Any) -> Decoder:
    """By command-line name: tval3, lifetime-fit, admm-net:RUN, unet:RUN, lifetime:RUN,
    zoo:NAME, onnx:MODEL.onnx; a decoder of cubes followed by ``+fit`` (``tval3+fit``,
    ``zoo:admm-lidar-delay+fit``) also gives ``depth``, its peaks refined in the tap domain.
    ``onset_ns``: the decays' onset when known, for the lifetime fits and a lifetime network on
    the fit's evidence (they fit only the IRF's width); any other decoder refuses it."""

def tval3(y: F32, sensor: Sensor, **options: Any) -> F32:
    """TVAL3: ``[M, H, W]`` → ``[T, H, W]`` (or batched). Options: mu, beta, maxit, tol,
    tol_inn, nonneg, tv_norm, weights, …"""

def lifetime_fit(y: F32, sensor: Sensor, *, clip_level: Optional[float] = None) -> Dict[str, F32]:
    """Lifetimes fitted to the tap images: ``lifetime [4, H, W]``, ``confidence``, ``intensity``;
    no lifetime where a tap reads ``clip_level``."""

def zoo_list() -> List[Dict[str, Any]]:
    """The zoo's entries: name, dir, decoder, domain, learned_codes, codes, epochs, validation, title, weights_bytes."""

class Dataset:
    """A dataset directory: manifest.json and .npy shards per split and field."""

    def __init__(self, path: PathLike) -> None: ...
    @property
    def manifest(self) -> Dict[str, Any]: ...
    @property
    def kind(self) -> str:
        """lidar or flim."""
    @property
    def splits(self) -> Dict[str, int]: ...
    @property
    def fields(self) -> Dict[str, List[int]]:
        """Per-item shapes: x [T, H, W]; LiDAR depth [2, H, W] (m); FLIm lifetime [H, W] (s), tau [3], …"""
    @property
    def bin_width_s(self) -> float: ...
    def load(self, split: str, field: str) -> F32:
        """One field of a whole split, ``[count, …]``."""
    def item(self, split: str, index: int) -> Dict[str, F32]: ...
    def items(self, split: str = "train") -> Iterator[Dict[str, F32]]:
        """Items in order, read shard by shard."""
    def __len__(self) -> int: ...

def generate_dataset(kind: str, out: PathLike, count: int, *, size: Tuple[int, int] = (64, 64), seed: int = 0, length: int = 32, clock_hz: float = ..., heterodyne: Optional[int] = None, oversample: Optional[int] = None, params: Optional[Dict[str, Any]] = None, force: bool = False) -> Dataset:
    """Randomised LiDAR or FLIm scenes (``tcsense dataset lidar|flim``); item i is a pure
    function of (seed, i); ``params`` overrides the generator's settings."""

def depth_map(x: F32, bin_width_s: float, *, max_peaks: int = 2, min_rel: float = 0.1, min_sep: int = 2) -> Tuple[F32, F32]:
    """``[T, H, W]`` → (range ``[K, H, W]`` in m, NaN where no return; amplitude ``[K, H, W]``)."""

def find_peaks(wave: F32, *, max_peaks: int = 2, min_rel: float = 0.1, min_sep: int = 2) -> List[Tuple[float, float]]:
    """Peaks of a waveform ``[T]``: (position in bins, amplitude), strongest first."""

def fit_lifetimes(x: F32, bin_width_s: float, *, components: str = "auto", irf_fwhm_s: Optional[float] = None, irf: Optional[F32] = None, min_intensity: float = 0.02) -> Dict[str, Any]:
    """Lifetimes of a cube ``[T, H, W]``: ``lifetimes [4, H, W]`` (τ_m, τ₁, τ₂ in s, α₁),
    ``background [H, W]``, ``phasor [2, H, W]``, ``onset_s``, ``irf_fwhm_s``."""

def phasors(x: F32, *, min_intensity: float = 0.02) -> F32:
    """Onset-referenced first-harmonic phasors ``[2, H, W]`` (g, s)."""

def point_cloud(depth: F32, *, fov_deg: float = 40.0) -> F32:
    """``[K, H, W]`` ranges → points ``[P, 4]`` (x, y, z in m, bounce)."""

def write_ply(path: PathLike, depth: F32, amplitude: F32, *, fov_deg: float = 40.0) -> int:
    """ASCII PLY of a range map; returns the number of points."""

def export_onnx(run: PathLike, out: PathLike, *, matrix_input: bool = False, calibration: Optional[PathLike] = None, from_taps: bool = False) -> int:
    """Export a run or ``zoo:NAME`` to ONNX (opset 17); returns the bytes written. ``from_taps``: a U-Net on
    the range fit's evidence as one graph from the tap images (evidence, network and refined first return)."""

def onnxruntime_version() -> str: ...

class OnnxModel:
    """An exported model in ONNX Runtime (the ``onnxruntime`` wheel's library)."""

    def __init__(self, path: PathLike, threads: int = 0) -> None: ...
    def run(self, y: F32) -> List[F32]:
        """Raw outputs ``[B, C, H, W]`` in the order of ``outputs``."""
    @property
    def outputs(self) -> List[str]: ...
    @property
    def metadata(self) -> Dict[str, Any]: ...
    @property
    def codes(self) -> Codes: ...

def calibrate(codes: Union[Codes, PathLike], sweep: PathLike, out: PathLike, *, irf: Union[str, PathLike, F32, None] = None, oversample: Optional[int] = None, heterodyne: Optional[int] = None, report: bool = True) -> Dict[str, Any]:
    """Calibrate from a laser-delay sweep (``tcsense calibrate``); returns calibration.json."""

def train(decoder: str, output: PathLike, *, progress: Optional[Callable[[Dict[str, Any]], Any]] = None, **options: Any) -> List[Dict[str, Any]]:
    """Train ``decoder`` ("admm-net", "unet", "lifetime") into the run ``output`` (``tcsense
    train``); options as the command line's flags with ``_`` for ``-`` (dataset, codes, epochs,
    lr, init_from, calibration, irf, resume, seed, crop=[h, w], sensor_residue=[g, p, d], …).
    ``progress(epoch)`` after every epoch. Returns the epochs trained (epoch, step,
    train_loss, seconds and the validation metrics)."""

def fine_tune(run: PathLike, output: PathLike, *, progress: Optional[Callable[[Dict[str, Any]], Any]] = None, **options: Any) -> List[Dict[str, Any]]:
    """Fine-tune a trained run or ``zoo:NAME`` into ``output`` (``train --init-from``): its
    network and architecture, with new codes, dataset, calibration or IRF."""

def simulate_sweep(sensor: Sensor, out: PathLike, *, size: Tuple[int, int] = (32, 32), average: int = 64, noise: bool = True, level: float = 0.7, adc: bool = False, png: bool = False, seed: int = 0, nonideal: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """A laser-delay sweep of a flat target through ``sensor`` with its ``nonideal``
    non-idealities (``tcsense simulate --sweep``), for ``calibrate``; returns sweep.json."""

def bringup(sweep: PathLike, codes: PathLike, out: PathLike, *, irf: str = "physical", heterodyne: Optional[int] = None, decoders: Optional[List[str]] = None, budget_minutes: float = 20.0, epochs: Optional[int] = None, scenes: int = 400, size: Tuple[int, int] = (64, 64), check_items: int = 8, seed: int = 1, quiet: bool = False) -> Dict[str, Any]:
    """A sensor brought up from a delay sweep (``tcsense bringup``): calibration, the zoo's
    decoders fine-tuned to it, ONNX models for its raw tap images, a check and
    ``out/report.html``; returns {report, models, steps}."""

def run_demo(out: PathLike, *, quick: bool = False, budget_minutes: Optional[float] = None, size: Optional[Tuple[int, int]] = None, scenes: Optional[int] = None, timing_size: Tuple[int, int] = (188, 212), seed: int = 1, quiet: bool = False) -> Dict[str, Any]:
    """The demo (``tcsense demo``) into ``out``; returns {report, seconds, resumed}."""
