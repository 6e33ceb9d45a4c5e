"""Mitsuba volpath (Monte Carlo) vs exp(-projection), the gaussian_medium plugin and the
exact line integrals of voxel grids used as the grid route's reference."""
import json

import numpy as np
import pytest

import mi_grg
import drjit as dr
import mitsuba as mi

from mi_grg.evaluation.crosscheck import compare, integrate_volume, render_crosscheck
from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry


def tiny_case(rng, n=4):
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(16, 16), sDetector=(3.0, 3.0),
                   nVoxel=(32, 32, 32), sVoxel=(2.0, 2.0, 2.0), offOrigin=(0.1, 0.0, -0.05),
                   angles=[0.2, 1.4, 2.5])
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    params = {"pos": np.asarray(geo.offOrigin) + rng.uniform(-0.35, 0.35, (n, 3)),
              "scales": rng.uniform(0.1, 0.25, (n, 3)), "q": q, "rho": rng.uniform(0.3, 2.0, n)}
    g = Gaussians.from_numpy(params["pos"], params["scales"], params["q"], params["rho"])
    return g, geo, params


def field64(params, x, extent):
    """sum_i rho_i exp(-m^2/2) [m <= extent] at points x [M, 3], float64."""
    w, qx, qy, qz = params["q"].T
    R = np.stack([1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                  2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                  2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)],
                 -1).reshape(-1, 3, 3)
    cov = R @ (params["scales"][:, :, None] ** 2 * np.transpose(R, (0, 2, 1)))
    A = np.linalg.inv(cov)
    out = np.zeros(len(x))
    for i in range(len(A)):
        d = x - params["pos"][i]
        m2 = np.einsum("ni,ij,nj->n", d, A[i], d)
        out += np.where(m2 <= extent ** 2, params["rho"][i] * np.exp(-0.5 * m2), 0.0)
    return out


@pytest.fixture
def medium(tmp_path, rng):
    g, geo, params = tiny_case(rng)
    g.save_npz(tmp_path / "g.npz")
    mi_grg.set_variant(mi.variant())
    return mi.load_dict({"type": "gaussian_medium", "filename": str(tmp_path / "g.npz"),
                         "extent": 4.0}), params


# ---------------------------------------------------------------- gaussian_medium
def test_gaussian_medium_extinction_matches_numpy(medium, rng):
    med, params = medium
    x = params["pos"][rng.integers(0, 4, 4000)] + rng.normal(size=(4000, 3)) * 0.3
    p = mi.Point3f(*[mi.Float(x[:, k]) for k in range(3)])
    ref = field64(params, x, 4.0)
    np.testing.assert_allclose(np.asarray(med.sigma_t(p)), ref, rtol=2e-5, atol=1e-6 * ref.max())
    mei = dr.zeros(mi.MediumInteraction3f, 4000)
    mei.p = p
    sigma_s, sigma_n, sigma_t = med.get_scattering_coefficients(mei)
    np.testing.assert_allclose(np.asarray(sigma_t[0]), ref, rtol=2e-5, atol=1e-6 * ref.max())
    assert not np.asarray(sigma_s[0]).any()
    np.testing.assert_allclose(np.asarray(sigma_n[0]) + np.asarray(sigma_t[0]), med.majorant,
                               rtol=1e-6)
    assert not med.is_homogeneous() and not med.has_spectral_extinction()


def test_gaussian_medium_majorant_is_a_safe_bound(medium, rng):
    med, params = medium
    # dense samples around every centre, where the maxima are
    x = params["pos"][rng.integers(0, 4, 200000)] + rng.normal(size=(200000, 3)) * 0.15
    peak = field64(params, np.concatenate([x, params["pos"]]), 4.0).max()
    assert peak <= med.majorant <= params["rho"].sum() * (1 + 1e-5)
    assert med.majorant < 1.5 * peak   # and a useful one (few null collisions)
    m = med.get_majorant(dr.zeros(mi.MediumInteraction3f, 1))
    assert float(m[0][0]) == pytest.approx(med.majorant, rel=1e-6)


def test_gaussian_medium_box(medium):
    med, params = medium
    lo, hi = np.asarray(med.bbox.min), np.asarray(med.bbox.max)
    assert np.all(lo < params["pos"].min(0)) and np.all(hi > params["pos"].max(0))
    ray = mi.Ray3f(mi.Point3f(-10, 0.05, 0.0), mi.Vector3f(1, 0, 0))
    hit, t0, t1 = med.intersect_aabb(ray)
    assert bool(hit[0])
    assert float(t0[0]) == pytest.approx(10 + lo[0], rel=1e-5)
    assert float(t1[0]) == pytest.approx(10 + hi[0], rel=1e-5)


# ---------------------------------------------------------------- grid line integrals
def test_integrate_volume_constant_is_chord_length():
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(9, 11), sDetector=(3.5, 3.5),
                   nVoxel=(6, 8, 5), sVoxel=(1.6, 2.0, 1.2), offOrigin=(0.1, -0.1, 0.05),
                   angles=[0.3, 2.0])
    proj = integrate_volume(np.full(geo.nVoxel, 0.7, np.float32), geo)
    o, d = geo.pixel_rays_numpy()
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    chord = np.maximum(np.maximum(t0, t1).min(-1) - np.maximum(np.minimum(t0, t1).max(-1), 0), 0)
    assert (chord > 0).any() and (chord == 0).any()
    np.testing.assert_allclose(proj, 0.7 * chord, rtol=1e-5, atol=1e-5)


def test_integrate_volume_matches_dense_trilinear_quadrature(rng):
    """Against scipy's trilinear interpolation (clamped at the edges) sampled densely."""
    from scipy.ndimage import map_coordinates
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(5, 6), sDetector=(2.5, 2.5),
                   nVoxel=(7, 9, 6), sVoxel=(1.4, 1.8, 1.2), offOrigin=(0.0, 0.1, -0.1),
                   angles=[0.7])
    vol = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    proj = integrate_volume(vol, geo)
    o, d = (a.reshape(-1, 3) for a in geo.pixel_rays_numpy())
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    t_in, t_out = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    ref = np.zeros(len(o))
    s = (np.arange(20000) + 0.5) / 20000   # midpoint rule
    for i in np.nonzero(t_out > t_in)[0]:
        t = t_in[i] + s * (t_out[i] - t_in[i])
        x = o[i] + t[:, None] * d[i]
        idx = (x - lo) / np.asarray(geo.dVoxel) - 0.5   # voxel-centre index coordinates
        vals = map_coordinates(vol.astype(np.float64), idx.T, order=1, mode="nearest")
        ref[i] = vals.mean() * (t_out[i] - t_in[i])
    np.testing.assert_allclose(proj.ravel(), ref, rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------- Monte Carlo vs closed form
def test_volpath_agrees_with_the_projector(tmp_path, rng):
    g, geo, _ = tiny_case(rng)
    res = render_crosscheck((g, geo), spp=256, out_dir=tmp_path, seed=3)
    for route in ("gaussian", "grid"):
        s = res["routes"][route]
        assert abs(s["z_mean"]) < 4.0, (route, s)
        assert 0.75 < s["z_rms"] < 1.3, (route, s)
        assert s["pixels_used"] > 300
    # the grid route's reference differs from the closed form only by discretisation
    assert res["routes"]["grid"]["grid_vs_projector"]["max_abs_T_difference"] < 0.05
    saved = json.loads((tmp_path / "crosscheck.json").read_text())
    assert saved["routes"]["gaussian"]["z_mean"] == res["routes"]["gaussian"]["z_mean"]
    for name in ("projector_T", "mc_gaussian", "diff_gaussian", "grid_T", "mc_grid",
                 "diff_grid"):
        assert (tmp_path / f"{name}.png").stat().st_size > 0
        img = np.asarray(mi.Bitmap(str(tmp_path / f"{name}.exr")))
        assert img.shape[:2] == (3 * 16, 16)


def test_monte_carlo_error_shrinks_as_one_over_sqrt_spp(tmp_path, rng):
    g, geo, _ = tiny_case(rng)
    rms = {}
    for spp in (64, 1024):
        res = render_crosscheck((g, geo), spp=spp, out_dir=tmp_path / str(spp), seed=11)
        rms[spp] = {r: s["rms_error"] for r, s in res["routes"].items()}
    for route in ("gaussian", "grid"):
        ratio = rms[64][route] / rms[1024][route]
        assert 3.2 < ratio < 5.0, (route, ratio)   # sqrt(16) = 4


def test_a_biased_estimate_is_detected(rng):
    """The statistics can fail: a 1 % transmittance bias at 4096 spp is many sigmas."""
    t = rng.uniform(0.3, 0.9, (3, 16, 16))
    noisy = t + rng.normal(size=t.shape) * np.sqrt(t * (1 - t) / 4096)
    assert abs(compare(noisy, t, 4096)["z_mean"]) < 4.0
    assert abs(compare(noisy * 0.99, t, 4096)["z_mean"]) > 10.0


def test_scene_file_route(tmp_path, rng):
    from mi_grg.data.scene import Scan, write_scan_xml
    g, geo, _ = tiny_case(rng, n=2)
    g.save_npz(tmp_path / "blobs.npz")
    mi_grg.set_variant(mi.variant())
    xml = write_scan_xml(Scan(geometry=geo, object={"type": "gaussian_medium",
                                                    "filename": "blobs.npz"}),
                         tmp_path / "scan.xml")
    res = render_crosscheck(xml, spp=16, out_dir=tmp_path / "out", routes=("gaussian",))
    assert res["n_gaussians"] == 2 and res["projection_shape"] == [3, 16, 16]
    assert abs(res["routes"]["gaussian"]["z_mean"]) < 5.0
    bad = write_scan_xml(Scan(geometry=geo, object={"type": "ct_phantom", "phantom": "shepp"}),
                         tmp_path / "phantom.xml")
    with pytest.raises(ValueError, match="gaussian_medium"):
        render_crosscheck(bad, spp=4, out_dir=tmp_path / "x")
