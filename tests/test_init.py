"""De-Init (mi_grg.training.init) vs scipy.ndimage and brute-force NumPy references."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import mi_grg
from mi_grg.training.init import (InitError, auto_density_rescale, default_radius, denoise_volume,
                         init_gaussians, sigma_d_voxels)


def _paper_filter(vol, sigma, r, mode):
    """The paper's filter written out: 1/Z sum_{j in [-r, r]^3} exp(-|j|^2 / (2 sigma^2))
    f(i + j), float64, outside values by ``mode`` (NumPy's pad names)."""
    pad = {"reflect": "symmetric", "nearest": "edge", "constant": "constant"}[mode]
    f = np.pad(np.asarray(vol, np.float64), r, mode=pad)
    j = np.arange(-r, r + 1)
    w = np.exp(-(j[:, None, None] ** 2 + j[None, :, None] ** 2 + j[None, None, :] ** 2)
               / (2 * sigma * sigma))
    w /= w.sum()
    nx, ny, nz = np.shape(vol)
    out = np.zeros((nx, ny, nz))
    for a in range(2 * r + 1):
        for b in range(2 * r + 1):
            for c in range(2 * r + 1):
                out += w[a, b, c] * f[a:a + nx, b:b + ny, c:c + nz]
    return out


@pytest.mark.parametrize("mode", ["reflect", "nearest", "constant"])
@pytest.mark.parametrize("sigma", [0.8, 1.6])
def test_denoise_is_the_papers_filter(rng, mode, sigma):
    # small axes (< radius 6 for sigma 1.6) exercise repeated reflections at the borders
    vol = rng.normal(size=(5, 14, 11)) + 2.0
    got = denoise_volume(vol, sigma, mode=mode)
    r = default_radius(sigma)
    ref = _paper_filter(vol.astype(np.float32), sigma, r, mode)
    assert got.dtype == np.float32 and got.shape == vol.shape
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6 * np.abs(vol).max())


def test_denoise_radius_and_identity(rng):
    vol = rng.random((8, 8, 8))
    got = denoise_volume(vol, 1.0, radius=3)          # the paper's "e.g. ceil(3 sigma)"
    ref = _paper_filter(vol.astype(np.float32), 1.0, 3, "reflect")
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_array_equal(denoise_volume(vol, None), vol.astype(np.float32))
    np.testing.assert_array_equal(denoise_volume(vol, 0), vol.astype(np.float32))
    # normalised kernel: a constant volume is unchanged (reflect / nearest borders)
    np.testing.assert_allclose(denoise_volume(np.full((5, 6, 7), 0.3), 2.0), 0.3, rtol=1e-6)
    with pytest.raises(InitError, match="NaN"):
        denoise_volume(np.full((3, 3, 3), np.nan), 1.0)
    with pytest.raises(InitError, match="mode"):
        denoise_volume(vol, 1.0, mode="wrap")


def _geometry(n=(12, 10, 8)):
    from mi_grg.core.geometry import circular_angles
    return mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(8, 8),
                           sDetector=(3.0, 3.0), nVoxel=n, sVoxel=(2.0, 1.6, 1.2),
                           offOrigin=(0.1, -0.2, 0.05), angles=circular_angles(3))


def _phantom(rng, shape):
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, s) for s in shape], indexing="ij")
    vol = (x ** 2 + y ** 2 + z ** 2 < 0.5).astype(np.float64)
    return vol + 0.05 * rng.normal(size=shape)


def _voxel_index(pos, geo):
    lo = np.asarray(geo.offOrigin) - np.asarray(geo.sVoxel) / 2
    f = (pos - lo) / np.asarray(geo.dVoxel) - 0.5
    idx = np.rint(f).astype(int)
    return idx, np.abs(f - idx).max()


def test_init_centres_densities_scales(variant, rng):
    geo = _geometry()
    vol = _phantom(rng, geo.nVoxel)
    info = {}
    g = init_gaussians(vol, geo, n_points=150, tau=0.2, sigma_d=1.5, seed=3, info=info)
    d = g.numpy()
    assert d["positions"].shape == (150, 3) and info["n_points"] == 150
    # reference denoised volume and candidate set
    den = gaussian_filter(vol.astype(np.float32).astype(np.float64), 1.5, mode="reflect",
                          truncate=default_radius(1.5) / 1.5)
    cand = den > 0.2 * den.max()
    idx, off = _voxel_index(d["positions"].astype(np.float64), geo)
    assert off < 1e-3                                   # voxel centres (no jitter)
    assert np.all(cand[idx[:, 0], idx[:, 1], idx[:, 2]])
    assert len({tuple(i) for i in idx}) == 150          # without replacement
    assert info["n_candidates"] == cand.sum()
    # densities: denoised value x 0.15
    np.testing.assert_allclose(d["densities"], 0.15 * den[idx[:, 0], idx[:, 1], idx[:, 2]],
                               rtol=1e-5)
    # scales: sqrt(mean squared distance to the 3 nearest others), clamped, isotropic
    p = d["positions"].astype(np.float64)
    d2 = ((p[:, None] - p[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    ref_s = np.sqrt(np.sort(d2, axis=1)[:, :3].mean(axis=1))
    ref_s = np.clip(ref_s, 0.0005 * 2.0, 0.5 * 2.0)
    for k in range(3):
        np.testing.assert_allclose(d["scales"][:, k], ref_s, rtol=1e-5)
    np.testing.assert_array_equal(d["rotations"], np.tile([1, 0, 0, 0], (150, 1)))


def test_init_cap_seed_and_plain_fdk(variant, rng):
    geo = _geometry()
    vol = _phantom(rng, geo.nVoxel)
    info = {}
    g = init_gaussians(vol, geo, n_points=10 ** 6, tau=0.3, sigma_d=None, info=info)
    cand = vol > 0.3 * vol.max()                         # no filter: the raw volume
    assert len(g) == cand.sum() == info["n_points"] and info["capped"]
    idx, _ = _voxel_index(g.numpy()["positions"].astype(np.float64), geo)
    assert np.array_equal(np.sort(np.ravel_multi_index(idx.T, vol.shape)),
                          np.flatnonzero(cand))
    a = init_gaussians(vol, geo, n_points=40, seed=5).numpy()
    b = init_gaussians(vol, geo, n_points=40, seed=5).numpy()
    c = init_gaussians(vol, geo, n_points=40, seed=6).numpy()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a["positions"], c["positions"])
    j = init_gaussians(vol, geo, n_points=40, seed=5, jitter=True).numpy()
    idx_j, off = _voxel_index(j["positions"].astype(np.float64), geo)
    assert 0.05 < off <= 0.5 + 1e-5                      # moved within the voxel


def test_init_errors(variant, rng):
    geo = _geometry()
    with pytest.raises(InitError, match="no positive voxel"):
        init_gaussians(np.zeros(geo.nVoxel), geo)
    with pytest.raises(InitError, match="no positive voxel"):
        init_gaussians(-np.ones(geo.nVoxel), geo, sigma_d=None)
    with pytest.raises(InitError, match="shape"):
        init_gaussians(np.ones((3, 3, 3)), geo)
    with pytest.raises(InitError, match="tau"):
        init_gaussians(np.ones(geo.nVoxel), geo, tau=1.0)


def test_auto_density_rescale_fits_the_field(rng):
    """The least-squares normal equation sum F (c F - v) = 0 holds for the FULL field
    (all pairs, brute force), up to the neglected far kernels."""
    geo = _geometry((20, 20, 20))
    vol = 1.0 + 0.3 * rng.random(geo.nVoxel)
    info = {}
    g = init_gaussians(vol, geo, n_points=400, sigma_d=None, density_rescale="auto",
                       seed=1, info=info).numpy()
    c = info["rescale"]
    p = g["positions"].astype(np.float64)
    s = g["scales"][:, 0].astype(np.float64)
    v = g["densities"] / c
    d2 = ((p[:, None] - p[None]) ** 2).sum(-1)
    field = (v[None] * np.exp(-0.5 * d2 / s[None] ** 2)).sum(1)
    assert abs(np.sum(field * (c * field - v))) < 1e-2 * np.sum(field * v)
    # random centres: the kernels overlap several-fold, so c is well below 1
    assert 0.02 < c < 0.5
    assert auto_density_rescale(p, s, v, n_neighbors=400) == pytest.approx(
        np.sum(v * field) / np.sum(field ** 2), rel=1e-6)


def test_sigma_d_is_a_length_scaled_to_the_grid():
    # the paper's 3 voxels at 256^3 are 3/256 of the longest edge on any grid
    assert sigma_d_voxels(3.0, (64, 64, 64)) == pytest.approx(0.75)
    assert sigma_d_voxels(3.0, (128, 96, 64), grid=256) == pytest.approx(1.5)
    assert sigma_d_voxels(3.0, (256, 256, 256)) == pytest.approx(3.0)
    assert sigma_d_voxels(3.0, (64, 64, 64), grid=0) == 3.0     # the case's own voxels
    assert sigma_d_voxels(0.0, (64, 64, 64)) == 0.0              # no filter (R2)
    for bad in (dict(sigma_d=-1.0), dict(sigma_d=float("nan")), dict(grid=-2), dict(grid=1.5)):
        kw = {"sigma_d": 3.0, "grid": 256, **bad}
        with pytest.raises(InitError, match="sigma_d"):
            sigma_d_voxels(kw["sigma_d"], (64, 64, 64), kw["grid"])
