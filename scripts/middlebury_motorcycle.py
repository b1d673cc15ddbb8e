#!/usr/bin/env python3
"""A real depth scene for the out-of-distribution benchmark: the Middlebury 2014 "Motorcycle"
stereo pair with its ground-truth disparities (Scharstein et al., GCPR 2014), as shipped
(4x down-sampled) inside the scikit-image wheel (skimage/data/motorcycle_disp.npz and
motorcycle_left.png; scikit-image is BSD-3-Clause). The wheel is read as a zip file, nothing
of scikit-image is imported.

Writes range.npy (metres along each pixel's ray; 0 where the disparity is unknown) and
albedo.npy (the left image's luminance in [0, 1]) of size H x W, by 5x5 block averages of a
centred crop (the default 96 x 128, the size of the issue's measurement).

usage: middlebury_motorcycle.py WHEEL OUT_DIR [H W]
"""
import io
import sys
import warnings
import zipfile

import numpy as np
from PIL import Image

# calibration of the 4x down-sampled images (skimage.data.stereo_motorcycle's docstring)
FOCAL_PX = 994.978
CX, CY = 311.193, 254.877
DOFFS_PX = 31.086
BASELINE_M = 0.193001
BLOCK = 5


def main():
    wheel, out = sys.argv[1], sys.argv[2]
    h, w = (int(sys.argv[3]), int(sys.argv[4])) if len(sys.argv) > 4 else (96, 128)
    with zipfile.ZipFile(wheel) as z:
        disp = np.load(io.BytesIO(z.read("skimage/data/motorcycle_disp.npz")))["arr_0"].astype(np.float64)
        left = np.asarray(Image.open(io.BytesIO(z.read("skimage/data/motorcycle_left.png"))).convert("L"), dtype=np.float64) / 255.0
    disp = disp.copy()
    rows, cols = disp.shape[:2]
    if disp.ndim == 3:
        disp = disp[..., 0]
    disp[~np.isfinite(disp)] = np.nan  # inf marks pixels without ground truth
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        z_m = FOCAL_PX * BASELINE_M / (disp + DOFFS_PX)
        rng = z_m * np.sqrt(1.0 + ((u - CX) / FOCAL_PX) ** 2 + ((v - CY) / FOCAL_PX) ** 2)
    rng[~np.isfinite(rng)] = np.nan
    ch, cw = h * BLOCK, w * BLOCK
    if ch > rows or cw > cols:
        sys.exit(f"{h}x{w} needs a {ch}x{cw} crop of the {rows}x{cols} image")
    r0, c0 = (rows - ch) // 2, (cols - cw) // 2
    def pool(a):
        blocks = a[r0:r0 + ch, c0:c0 + cw].reshape(h, BLOCK, w, BLOCK)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-unknown blocks give NaN: no return
            return np.nanmean(blocks, axis=(1, 3))
    rng_s, alb_s = pool(rng), pool(left)
    valid = np.isfinite(rng_s)
    rng_s[~valid] = 0.0
    np.save(f"{out}/range.npy", rng_s.astype(np.float32))
    np.save(f"{out}/albedo.npy", np.clip(alb_s, 0.02, 1.0).astype(np.float32))
    print(f"{out}: {h}x{w}, range {rng_s[valid].min():.3f}-{rng_s[valid].max():.3f} m, {valid.mean() * 100:.1f} % of pixels with a return")


if __name__ == "__main__":
    main()
