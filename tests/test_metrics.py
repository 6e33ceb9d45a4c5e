"""Metrics against independent references: scikit-image, a float64 direct-sum SSIM, closed
forms, and per-slice loops written out here."""
import math

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from mi_grg.evaluation import metrics


def _smooth_pair(rng, shape):
    """A structured image/volume in [0, 1] and a noisy copy (SSIM well away from 0 and 1)."""
    a = rng.random(shape)
    for ax in range(len(shape)):
        a = (a + np.roll(a, 1, ax) + np.roll(a, -1, ax)) / 3
    a = (a - a.min()) / (a.max() - a.min())
    return a, np.clip(a + 0.1 * rng.standard_normal(shape), 0, 1)


def _ssim_direct(x, y, L=1.0, size=11, sigma=1.5):
    """Zero-padded windowed SSIM by explicit sums over every window (no convolution)."""
    h, w = x.shape
    r = size // 2
    k = np.arange(-r, r + 1)
    g = np.exp(-(k ** 2) / (2 * sigma ** 2))
    W = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    total = 0.0
    for i in range(h):
        for j in range(w):
            sx = sy = sxx = syy = sxy = 0.0
            for di in range(-r, r + 1):
                for dj in range(-r, r + 1):
                    ii, jj = i + di, j + dj
                    if 0 <= ii < h and 0 <= jj < w:   # outside: zero padding adds nothing
                        wt = W[di + r, dj + r]
                        a, b = x[ii, jj], y[ii, jj]
                        sx += wt * a
                        sy += wt * b
                        sxx += wt * a * a
                        syy += wt * b * b
                        sxy += wt * a * b
            vx, vy, cxy = sxx - sx * sx, syy - sy * sy, sxy - sx * sy
            total += ((2 * sx * sy + c1) * (2 * cxy + c2)) / (
                (sx * sx + sy * sy + c1) * (vx + vy + c2))
    return total / (h * w)


# ---------------------------------------------------------------- 2-D SSIM
def test_window_matches_reference_formula():
    g = metrics.gaussian_window_1d()
    assert g.shape == (11,)
    assert g.sum() == pytest.approx(1.0, abs=1e-15)
    assert g[0] / g[5] == pytest.approx(math.exp(-25 / (2 * 1.5 ** 2)), rel=1e-12)


def test_ssim_2d_matches_skimage_in_the_interior(rng):
    a, b = _smooth_pair(rng, (40, 37))
    _, S = structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1.0, full=True)
    ours = metrics.ssim_map_2d(a, b)
    assert ours.shape == a.shape
    assert metrics.ssim_2d(a, b) == pytest.approx(ours.mean(), abs=1e-14)
    np.testing.assert_allclose(ours[5:-5, 5:-5], S[5:-5, 5:-5], atol=1e-6, rtol=0)
    # At the border zero padding (theirs) and skimage's reflection differ: both maps are
    # really the same-size, border-included kind.
    assert np.max(np.abs(ours[:5] - S[:5])) > 1e-3


@pytest.mark.parametrize("data_range", [1.0, 4.0])
def test_ssim_2d_matches_direct_sum(rng, data_range):
    a, b = _smooth_pair(rng, (9, 13))
    a, b = a * data_range, b * data_range
    assert metrics.ssim_2d(a, b, data_range) == pytest.approx(
        _ssim_direct(a, b, data_range), abs=1e-12)


def test_ssim_2d_identity_symmetry_and_range(rng):
    a, b = _smooth_pair(rng, (20, 24))
    assert metrics.ssim_2d(a, a) == pytest.approx(1.0, abs=1e-12)
    assert metrics.ssim_2d(a, b) == pytest.approx(metrics.ssim_2d(b, a), abs=1e-14)
    assert 0.0 < metrics.ssim_2d(a, b) < 0.99


def test_ssim_2d_default_is_their_fixed_constants(rng):
    """Their ssim hard-codes C1 = 0.01^2, C2 = 0.03^2: scaling both images changes it."""
    a, b = _smooth_pair(rng, (16, 16))
    assert metrics.ssim_2d(3 * a, 3 * b) != pytest.approx(metrics.ssim_2d(a, b), abs=1e-4)
    assert metrics.ssim_2d(3 * a, 3 * b, 3.0) == pytest.approx(metrics.ssim_2d(a, b), abs=1e-12)


# ---------------------------------------------------------------- volumes
def test_psnr_3d_hand_formula(rng):
    gt = rng.random((6, 7, 8))
    pred = gt + 0.03 * rng.standard_normal(gt.shape)
    mse = float(np.sum((pred - gt) ** 2)) / gt.size
    assert metrics.psnr_3d(pred, gt) == pytest.approx(10 * math.log10(1 / mse), rel=1e-12)
    assert metrics.psnr_3d(pred * 2, gt * 2, data_range=2.0) == pytest.approx(
        10 * math.log10(1 / mse), rel=1e-12)
    assert metrics.psnr_3d(gt, gt) == math.inf


def test_ssim_3d_skips_empty_gt_slices(rng):
    gt, pred = _smooth_pair(rng, (14, 15, 16))
    gt[:4] = 0.0          # empty x-slices 0..3; pred is non-zero there
    gt[:, -2:] = 0.0      # empty y-slices
    pred[:4] += 0.3

    def axis_mean(axis, skip_empty):
        vals = []
        for i in range(gt.shape[axis]):
            g, p = np.take(gt, i, axis), np.take(pred, i, axis)
            if skip_empty and not g.max() > 0:
                continue
            vals.append(metrics.ssim_2d(p, g))
        return np.mean(vals)

    expected = [axis_mean(ax, True) for ax in range(3)]
    got = metrics.ssim_3d_axes(pred, gt)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    assert metrics.ssim_3d(pred, gt) == pytest.approx(np.mean(expected), abs=1e-12)
    # Including the empty slices would change x and y (z has none empty).
    assert abs(axis_mean(0, False) - expected[0]) > 1e-3
    assert abs(axis_mean(1, False) - expected[1]) > 1e-3


def test_ssim_3d_batches_agree(rng, monkeypatch):
    """Batching over slices (memory bound) must not change the result."""
    gt, pred = _smooth_pair(rng, (9, 10, 11))
    whole = metrics.ssim_3d_axes(pred, gt)
    monkeypatch.setattr(metrics, "_CHUNK_PIXELS", 150)   # 1 slice per batch
    np.testing.assert_allclose(metrics.ssim_3d_axes(pred, gt), whole, atol=1e-14)


def test_ssim_3d_all_empty_gt_raises():
    with pytest.raises(ValueError, match="no slice with max > 0"):
        metrics.ssim_3d(np.ones((4, 4, 4)), np.zeros((4, 4, 4)))


# ---------------------------------------------------------------- projections
def test_projection_metrics_normalise_each_by_its_own_max(rng):
    gt = rng.random((4, 12, 14)) + 0.1
    # pred = per-view scaled copy: after own-max normalisation it equals gt exactly.
    pred = gt * np.array([0.5, 2.0, 3.0, 7.0])[:, None, None]
    assert metrics.ssim_proj(pred, gt) == pytest.approx(1.0, abs=1e-12)
    assert metrics.psnr_proj(pred, gt) == math.inf

    noisy = np.abs(pred + 0.05 * rng.standard_normal(pred.shape))
    expected_psnr, expected_ssim = [], []
    for p, g in zip(noisy, gt):
        pn, gn = p / p.max(), g / g.max()
        expected_psnr.append(10 * math.log10(1.0 / np.mean((pn - gn) ** 2)))
        expected_ssim.append(_ssim_direct(pn, gn))
    assert metrics.psnr_proj(noisy, gt) == pytest.approx(np.mean(expected_psnr), rel=1e-12)
    assert metrics.ssim_proj(noisy, gt) == pytest.approx(np.mean(expected_ssim), abs=1e-12)


def test_projection_metrics_skip_views_with_empty_gt(rng):
    gt = rng.random((3, 8, 9)) + 0.1
    pred = np.abs(gt + 0.05 * rng.standard_normal(gt.shape))
    gt0 = gt.copy()
    gt0[1] = 0.0
    views = metrics.psnr_proj_views(pred, gt0)
    assert np.isnan(views[1]) and np.all(np.isfinite(views[[0, 2]]))
    full = metrics.psnr_proj_views(pred, gt)
    assert metrics.psnr_proj(pred, gt0) == pytest.approx(np.mean(full[[0, 2]]), rel=1e-12)
    ss = metrics.ssim_proj_views(pred, gt0)
    assert metrics.ssim_proj(pred, gt0) == pytest.approx(np.mean(ss[[0, 2]]), rel=1e-12)


def test_projection_pred_without_positive_max_warns(rng):
    gt = rng.random((2, 6, 6)) + 0.1
    pred = gt.copy()
    pred[0] = 0.0
    with pytest.warns(RuntimeWarning, match="max <= 0"):
        v = metrics.psnr_proj_views(pred, gt)
    gn = gt[0] / gt[0].max()
    assert v[0] == pytest.approx(10 * math.log10(1 / np.mean(gn ** 2)), rel=1e-12)


def test_metric_report_keys(rng):
    gt, pred = _smooth_pair(rng, (8, 9, 10))
    rep = metrics.metric_report(pred, gt, pred + 0.1, gt + 0.1)
    assert set(rep) == {"psnr_3d", "ssim_3d", "ssim_3d_x", "ssim_3d_y", "ssim_3d_z",
                        "psnr_2d", "ssim_2d"}
    assert rep["psnr_3d"] == pytest.approx(metrics.psnr_3d(pred, gt))
    assert rep["ssim_3d"] == pytest.approx(metrics.ssim_3d(pred, gt))


# ---------------------------------------------------------------- validation
@pytest.mark.parametrize("fn,nd", [(metrics.psnr_3d, 3), (metrics.ssim_3d, 3),
                                   (metrics.ssim_2d, 2), (metrics.psnr_proj, 3),
                                   (metrics.ssim_proj, 3)])
def test_validation(fn, nd):
    good = np.ones((5,) * nd)
    with pytest.raises(ValueError, match="shape"):
        fn(np.ones((5,) * (nd - 1) + (4,)), good)
    with pytest.raises(ValueError, match=f"{nd}-D"):
        fn(np.ones((5,) * (nd + 1)), np.ones((5,) * (nd + 1)))
    bad = good.copy()
    bad.flat[3] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        fn(bad, good)
    bad.flat[3] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        fn(good, bad)


def test_data_range_validation():
    with pytest.raises(ValueError, match="data_range"):
        metrics.psnr_3d(np.ones((2, 2, 2)), np.ones((2, 2, 2)), data_range=0)
