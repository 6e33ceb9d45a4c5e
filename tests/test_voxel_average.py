"""Gaussians blurred to voxel averages (mi_grg.core.voxel_average), against float64 brute
force: the box average of a Gaussian over each voxel, the covariance sum, the mass."""
import numpy as np
import pytest

import mi_grg
from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry
from mi_grg.core.voxel_average import (_matrices, _quaternions, convolve_gaussians,
                                       voxel_average, voxel_variance)


@pytest.fixture(autouse=True)
def _llvm():
    mi_grg.set_variant("llvm_ad_mono")


def _geo(n=(16, 16, 16), s=(2.0, 2.0, 2.0)):
    return Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(24, 24), sDetector=(4.0, 4.0), nVoxel=n,
                    sVoxel=s, angles=np.linspace(0, np.pi, 4, endpoint=False))


def _box_average(mean, cov, rho, geo, sub=8):
    """Float64 brute force: each voxel's average of the Gaussian over sub^3 points."""
    h = np.asarray(geo.sVoxel) / np.asarray(geo.nVoxel)
    lo = -np.asarray(geo.sVoxel) / 2 + np.asarray(geo.offOrigin)
    axes = [lo[a] + (np.arange(geo.nVoxel[a] * sub) + 0.5) * h[a] / sub for a in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1) - mean
    m2 = np.einsum("...i,ij,...j->...", X, np.linalg.inv(cov), X)
    f = rho * np.exp(-0.5 * m2)
    n = geo.nVoxel
    return f.reshape(n[0], sub, n[1], sub, n[2], sub).mean(axis=(1, 3, 5))


def _one(s, q=(1.0, 0, 0, 0), p=(0.03, -0.02, 0.05)):
    return Gaussians.from_numpy(np.array([p]), np.array([s]), np.array([q], float),
                                np.array([1.0]))


@pytest.mark.parametrize("width", [0.8, 1.5])
def test_centre_samples_of_the_blurred_field_are_the_voxel_averages(width):
    """A Gaussian about a voxel wide: its box averages (float64 brute force) are matched by
    the blurred Gaussian's voxel-centre values far better than by its own."""
    from mi_grg.core.voxelizer import voxelize
    geo = _geo()
    h = 2.0 / 16
    q = np.array([0.9, 0.2, -0.3, 0.25]); q /= np.linalg.norm(q)
    s = np.array([width, 0.7 * width, 1.2 * width]) * h
    g = _one(s, q)
    R = _matrices(q[None])[0]
    ref = _box_average(np.array([0.03, -0.02, 0.05]), R @ np.diag(s * s) @ R.T, 1.0, geo)
    plain = voxelize(g, geo, extent=6.0)
    blurred = voxelize(voxel_average(g, geo, 1.0), geo, extent=6.0)
    err_plain = np.abs(plain - ref).max()
    err_blur = np.abs(blurred - ref).max()
    assert err_blur < 0.35 * err_plain, (err_blur, err_plain)
    assert err_blur < 0.04 * ref.max()


def test_covariance_adds_and_mass_is_kept_on_non_cubic_voxels():
    """Anisotropic voxels (the eigen path): Sigma' = Sigma + diag(v) in float64, the mass
    rho sqrt(det Sigma) unchanged; cubic voxels (the isotropic path) likewise."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4)); q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = rng.uniform(0.02, 0.2, size=(50, 3))
    g = Gaussians.from_numpy(rng.uniform(-0.5, 0.5, (50, 3)), s, q, rng.uniform(0.1, 2, 50))
    for geo in (_geo(n=(16, 20, 12), s=(2.0, 1.6, 2.4)), _geo()):
        v = voxel_variance(geo, 0.75)
        out = convolve_gaussians(g, v).numpy()
        R, R2 = _matrices(q), _matrices(out["rotations"].astype(np.float64))
        cov = np.einsum("nik,nk,njk->nij", R, s * s, R) + np.diag(v)
        s2 = out["scales"].astype(np.float64)
        cov2 = np.einsum("nik,nk,njk->nij", R2, s2 * s2, R2)
        np.testing.assert_allclose(cov2, cov, rtol=1e-4, atol=1e-7)
        mass = g.numpy()["densities"] * np.prod(s, 1)
        np.testing.assert_allclose(out["densities"] * np.prod(s2, 1), mass, rtol=1e-5)


def test_quaternions_of_rotation_matrices_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(200, 4)); q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]   # each Shepperd case
    back = _quaternions(_matrices(q))
    sign = np.sign(np.sum(back * q, axis=1, keepdims=True))
    np.testing.assert_allclose(back * sign, q, atol=1e-12)


def test_zero_share_is_the_identity_and_bad_shares_are_refused():
    g = _one(np.array([0.1, 0.1, 0.1]))
    assert voxel_average(g, _geo(), 0.0) is g
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="voxel_average must be"):
            voxel_average(g, _geo(), bad)
