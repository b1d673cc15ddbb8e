"""Products of cubes: depth with sub-bin precision, peaks, point clouds, lifetimes, phasors."""

import numpy as np
import pytest

import tcsense

C = 299_792_458.0


def gaussian_cube(centres, t=32, sigma=1.2):
    """[T, 2, 2] with one Gaussian pulse per pixel at `centres` (bins)."""
    j = np.arange(t)[:, None, None]
    c = np.asarray(centres, dtype=np.float64).reshape(1, 2, 2)
    return np.exp(-0.5 * ((j - c) / sigma) ** 2).astype(np.float32)


def test_depth_has_sub_bin_precision():
    bw = 1.6474e-9
    centres = [[5.0, 7.3], [12.6, 20.45]]
    depth, amp = tcsense.depth_map(gaussian_cube(centres), bw, max_peaks=2)
    assert depth.shape == (2, 2, 2) and amp.shape == (2, 2, 2)
    want = C * (np.asarray(centres) + 0.5) * bw / 2
    np.testing.assert_allclose(depth[0], want, atol=C * 0.05 * bw / 2)
    assert np.isnan(depth[1]).all()


def test_peaks_and_point_cloud(tmp_path):
    wave = gaussian_cube([[5.0, 5.0], [5.0, 5.0]])[:, 0, 0] + 0.5 * gaussian_cube([[17.0, 17.0], [17.0, 17.0]])[:, 0, 0]
    peaks = tcsense.find_peaks(wave)
    assert [round(p) for p, _ in peaks] == [5, 17]
    depth = np.full((2, 4, 4), np.nan, dtype=np.float32)
    depth[0] = 3.0
    depth[1, :2] = 5.0
    pts = tcsense.point_cloud(depth)
    assert pts.shape == (16 + 8, 4)
    np.testing.assert_allclose(np.linalg.norm(pts[:, :3], axis=1), np.where(pts[:, 3] == 0, 3.0, 5.0), rtol=1e-5)
    assert tcsense.write_ply(tmp_path / "c.ply", depth, np.ones_like(depth)) == 24
    assert (tmp_path / "c.ply").read_text().startswith("ply\n")


def test_lifetimes_of_a_decay():
    # a single exponential of τ = 2.5 ns on a 256-bin, 12.5 ns cycle, onset at 1 ns
    t, period = 256, 12.5e-9
    bw = period / t
    tau = 2.5e-9
    times = (np.arange(t) + 0.5) * bw
    dt = (times - 1e-9) % period
    wave = np.exp(-dt / tau) / (1 - np.exp(-period / tau))
    x = np.repeat(wave[:, None, None], 4, axis=1).repeat(4, axis=2).astype(np.float32)
    fit = tcsense.fit_lifetimes(x, bw, components="1", irf_fwhm_s=0.0)
    assert fit["lifetimes"].shape == (4, 4, 4)
    np.testing.assert_allclose(fit["lifetimes"][0], tau, rtol=0.03)
    ph = tcsense.phasors(x)
    assert ph.shape == (2, 4, 4)
    # a single exponential lies on the universal semicircle: g² + s² = g
    g, s = ph[0], ph[1]
    np.testing.assert_allclose(g * g + s * s, g, atol=0.03)


def test_a_cube_decoder_with_fit_gives_ranges():
    # `NAME+fit`: the zoo ADMM-Net's cube and, beside it, its peaks refined in the tap domain
    plain = tcsense.open_decoder("zoo:admm-lidar-delay")
    dec = tcsense.open_decoder("zoo:admm-lidar-delay+fit")
    # a wall at 9.3 bins on a dim background (the datasets' sub-bin impulse)
    tau = 9.3
    x = np.full((32, 8, 8), 0.01, dtype=np.float32)
    x[8] += 0.2
    x[9] += 0.8
    y = dec.sensor.forward(x)
    out = dec.decode(y)
    np.testing.assert_array_equal(out["cube"], plain.decode(y)["cube"])
    assert out["depth"].shape == (2, 8, 8) and out["confidence"].shape == (2, 8, 8)
    dz = C * dec.sensor.bin_width_s / 2
    peaks = np.abs(tcsense.depth_map(out["cube"], dec.sensor.bin_width_s)[0][0] / dz - tau)
    fitted = np.abs(out["depth"][0] / dz - tau)
    # the ranges are in metres from the start of the cycle, as depth_map's: within a bin
    # (the fit's precision is tested in the Rust suite; here its wiring)
    assert np.median(fitted) < 0.5 and np.median(peaks) < 0.5, (fitted, peaks)


def test_a_known_onset_reaches_a_lifetime_network():
    # a lifetime network on the fit's evidence takes the decays' onset when it is known, and
    # reads the lifetimes nearer the truth than at a wrong one; a decoder that fits none refuses it
    name = "zoo:lifetime-flim-evidence-fast"
    known = tcsense.open_decoder(name, onset_ns=30.0)
    late = tcsense.open_decoder(name, onset_ns=34.0)
    sensor = known.sensor
    t_bins, dt = sensor.bins, sensor.bin_width_s
    period = t_bins * dt
    tau = 2.5e-9
    t = (np.arange(t_bins) + 0.5) * dt
    decay = np.exp(-((t - 30e-9) % period) / tau)
    x = (decay[:, None, None] * np.linspace(0.5, 1.0, 16 * 16).reshape(1, 16, 16)).astype(np.float32)
    y = sensor.measure(x, noise=True, seed=1, signal_fraction=0.1)

    def err(dec):
        return np.nanmean(np.abs(dec.decode(y)["lifetime"][0] - tau))

    assert err(known) < 0.5 * err(late)
    with pytest.raises(tcsense.TcsenseError, match="onset"):
        tcsense.open_decoder("tval3", onset_ns=30.0)
    with pytest.raises(tcsense.TcsenseError, match="onset"):
        tcsense.open_decoder(name, onset_ns=float("nan"))


def test_clipped_pixels_get_no_range():
    # a tap at the clip level: that pixel's ranges NaN and confidences 0, the cube untouched,
    # every other pixel as decoded without the level
    dec = tcsense.open_decoder("zoo:admm-lidar-delay+fit")
    x = np.full((32, 8, 8), 0.01, dtype=np.float32)
    x[9] += np.linspace(0.2, 1.0, 64, dtype=np.float32).reshape(8, 8)
    y = dec.sensor.forward(x)
    level = float(np.quantile(y, 0.9))
    out, plain = dec.decode(y, clip_level=level), dec.decode(y)
    unread = (y >= level * (1 - 1e-6)).any(axis=0)
    assert 0 < unread.sum() < 64
    assert np.isnan(out["depth"][:, unread]).all() and (out["confidence"][:, unread] == 0).all()
    np.testing.assert_array_equal(out["depth"][:, ~unread], plain["depth"][:, ~unread])
    np.testing.assert_array_equal(out["cube"], plain["cube"])
    with pytest.raises(Exception, match="clip_level"):
        dec.decode(y, clip_level=-1.0)
