"""Losses (mi_grg.training.losses) vs float64 NumPy references and central finite differences."""
import numpy as np
import pytest

import mi_grg  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_grg.training import losses


# ------------------------------------------------------------------ float64 references
def np_ssim(a, b, size=11, sigma=1.5):
    """Direct windowed sums: for every pixel, the 2-D window over its size x size
    neighbourhood, pixels outside the image counted as 0 (conv2d zero padding)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.ndim == 2:
        a, b = a[None], b[None]
    r = size // 2
    x = np.arange(size) - r
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    n, h, w = a.shape
    pa = np.zeros((n, h + 2 * r, w + 2 * r))
    pb = np.zeros_like(pa)
    pa[:, r:r + h, r:r + w] = a
    pb[:, r:r + h, r:r + w] = b
    mu1 = np.zeros((n, h, w))
    mu2, e11, e22, e12 = (np.zeros_like(mu1) for _ in range(4))
    for dv in range(size):
        for du in range(size):
            wgt = g[dv] * g[du]
            sa = pa[:, dv:dv + h, du:du + w]
            sb = pb[:, dv:dv + h, du:du + w]
            mu1 += wgt * sa
            mu2 += wgt * sb
            e11 += wgt * sa * sa
            e22 += wgt * sb * sb
            e12 += wgt * sa * sb
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s1, s2, s12 = e11 - mu1 ** 2, e22 - mu2 ** 2, e12 - mu1 * mu2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s1 + s2 + c2))
    return m.mean()


def np_tv(v, reduction="mean"):
    v = np.asarray(v, np.float64)
    tot = sum(np.abs(np.diff(v, axis=k)).sum() for k in range(3))
    cnt = sum(np.diff(v, axis=k).size for k in range(3))
    return tot / cnt if reduction == "mean" else tot


def tensor(a):
    return mi.TensorXf(np.asarray(a, np.float32))


def ad_grad(fn, a_np, b_np=None):
    """Value and gradient of fn(tensor(a), tensor(b)) w.r.t. a (Dr.Jit AD)."""
    a = tensor(a_np)
    dr.enable_grad(a)
    val = fn(a) if b_np is None else fn(a, tensor(b_np))
    dr.backward(val)
    return float(val[0]), np.asarray(dr.grad(a), np.float64).reshape(a_np.shape)


def fd_grad(fn, a, entries, h=1e-6):
    """Central differences of the float64 reference at the given flat entries."""
    a = np.asarray(a, np.float64)
    out = []
    for e in entries:
        ap, am = a.copy().reshape(-1), a.copy().reshape(-1)
        ap[e] += h
        am[e] -= h
        out.append((fn(ap.reshape(a.shape)) - fn(am.reshape(a.shape))) / (2 * h))
    return np.array(out)


# ------------------------------------------------------------------ tests
def test_l1_value_and_gradient(variant, rng):
    a = rng.random((2, 5, 6)).astype(np.float32)
    b = rng.random((2, 5, 6)).astype(np.float32)
    val, g = ad_grad(losses.l1, a, b)
    assert val == pytest.approx(np.abs(a.astype(np.float64) - b).mean(), rel=1e-6)
    np.testing.assert_allclose(g, np.sign(a - b) / a.size, rtol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        losses.l1(tensor(a), tensor(b[:1]))


def test_rms_value_and_gradient(variant, rng):
    """Against float64: sqrt(mean r^2) and its gradient r / (n rms); finite at r = 0."""
    a = rng.random((2, 5, 6)).astype(np.float32)
    b = rng.random((2, 5, 6)).astype(np.float32)
    r = a.astype(np.float64) - b
    ref = np.sqrt(np.mean(r * r))
    val, g = ad_grad(losses.rms, a, b)
    assert val == pytest.approx(ref, rel=1e-6)
    np.testing.assert_allclose(g, r / (a.size * ref), rtol=1e-5)
    val, g = ad_grad(losses.rms, a, a)
    assert val == pytest.approx(np.sqrt(losses.RMS_FLOOR), rel=1e-3)
    assert np.all(np.isfinite(g)) and not np.any(g)
    with pytest.raises(ValueError, match="shape"):
        losses.rms(tensor(a), tensor(b[:1]))


@pytest.mark.parametrize("shape", [(2, 13, 17), (1, 6, 9), (20, 31)])
def test_ssim_value_matches_direct_windowed_sum(variant, rng, shape):
    a = rng.random(shape).astype(np.float32)
    b = np.clip(a + 0.2 * rng.normal(size=shape), 0, 1).astype(np.float32)
    got = float(losses.ssim(tensor(a), tensor(b))[0])
    ref = np_ssim(a, b)
    assert got == pytest.approx(ref, abs=2e-6)
    assert float(losses.dssim(tensor(a), tensor(b))[0]) == pytest.approx(1 - ref, abs=2e-6)
    # identical images: SSIM exactly 1 up to rounding
    assert float(losses.dssim(tensor(a), tensor(a))[0]) == pytest.approx(0.0, abs=1e-6)


def test_projection_loss_is_l1_plus_weighted_dssim(variant, rng):
    a = rng.random((1, 12, 15)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.normal(size=a.shape), 0, 1).astype(np.float32)
    l1_ref = float(np.mean(np.abs(a - b)))
    d_ref = 1 - np_ssim(a, b)
    got = float(losses.projection_loss(tensor(a), tensor(b), 0.25)[0])
    assert got == pytest.approx(l1_ref + 0.25 * d_ref, abs=2e-6)
    assert float(losses.projection_loss(tensor(a), tensor(b), 0.0)[0]) == pytest.approx(
        l1_ref, abs=1e-7)
    rms_ref = float(np.sqrt(np.mean(np.square(a.astype(np.float64) - b))))
    got = float(losses.projection_loss(tensor(a), tensor(b), 0.25, "rms")[0])
    assert got == pytest.approx(rms_ref + 0.25 * d_ref, abs=2e-6)
    with pytest.raises(ValueError, match="data_loss must be one of l1, rms"):
        losses.projection_loss(tensor(a), tensor(b), 0.25, "l2")


def test_ssim_agrees_with_the_metric(variant, rng):
    """Same window/padding/constants as mi_grg.evaluation.metrics' SSIM (the evaluation metric)."""
    from mi_grg.evaluation import metrics
    a = rng.random((24, 19)).astype(np.float32)
    b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1).astype(np.float32)
    assert float(losses.ssim(tensor(a), tensor(b))[0]) == pytest.approx(
        float(metrics.ssim_2d(a, b)), abs=2e-6)


def test_dssim_gradient_vs_finite_differences(variant, rng):
    shape = (2, 7, 8)
    a = rng.random(shape)
    b = np.clip(a + 0.3 * rng.normal(size=shape), 0, 1)
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    _, g = ad_grad(losses.dssim, a32, b32)
    entries = rng.choice(a.size, 12, replace=False)
    fd = fd_grad(lambda x: 1 - np_ssim(x, b32), a32, entries)
    scale = np.abs(fd).max()
    np.testing.assert_allclose(g.reshape(-1)[entries], fd, rtol=2e-3, atol=2e-3 * scale)


def test_tv_value_and_gradient(variant, rng):
    v = rng.random((4, 5, 6)).astype(np.float32)
    for red in ("mean", "sum"):
        got = float(losses.tv_3d(tensor(v), reduction=red)[0])
        assert got == pytest.approx(np_tv(v, red), rel=2e-6)
    _, g = ad_grad(losses.tv_3d, v)
    entries = rng.choice(v.size, 15, replace=False)
    fd = fd_grad(np_tv, v, entries)
    np.testing.assert_allclose(g.reshape(-1)[entries], fd, rtol=1e-4, atol=1e-7)
    # a constant volume has zero TV; a degenerate axis contributes nothing
    assert float(losses.tv_3d(tensor(np.full((3, 3, 3), 0.7)))[0]) == 0.0
    flat = rng.random((3, 1, 4)).astype(np.float32)
    assert float(losses.tv_3d(tensor(flat))[0]) == pytest.approx(np_tv(flat), rel=2e-6)
    with pytest.raises(ValueError, match="3-D"):
        losses.tv_3d(tensor(v[0]))
