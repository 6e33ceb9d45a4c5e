"""mi_grg.data.volume_phantom: fine-step trilinear projections of voxel volumes, ground truth on a
coarser grid, cases from data files. References: closed-form chord lengths (float64 slab
method), the closed-form line integral of a Gaussian blob, scipy's map_coordinates for the
trilinear object, and step halving."""
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.special import erf

import mi_grg  # noqa: F401  (first: sets up LLVM for Dr.Jit)
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.noise import NoiseModel
from mi_grg.data.volume_phantom import (DATA_ENV, average_to_grid, block_average, data_dir,
                                   simulate_volume_case, volume_line_integrals)


def _geo(mode="cone", n=(16, 16, 16), det=(20, 28), views=3):
    s = {"cone": (4.2, 4.2), "parallel": (3.0, 3.0)}[mode]
    return Geometry(mode=mode, DSD=7.0, DSO=5.0, nDetector=det, sDetector=s, nVoxel=n,
                    sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(views) + 0.3)


def _chords(geo):
    """float64 [view, v, u]: ray length inside the volume box (slab method)."""
    o, d = geo.pixel_rays_numpy()
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    near = np.where(np.isnan(ta), -np.inf, np.minimum(ta, tb)).max(-1)
    far = np.where(np.isnan(tb), np.inf, np.maximum(ta, tb)).min(-1)
    if geo.mode == "cone":
        near = np.maximum(near, 0.0)
    return np.clip(far - near, 0.0, None)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_constant_volume_is_exact(variant, mode):
    # A constant volume is a constant density on the box: line integral = c * chord. The
    # midpoint rule integrates a constant exactly, so only float32 round-off remains.
    geo = _geo(mode)
    c = 0.7
    vol = np.full((12, 10, 8), c, np.float32)        # anisotropic source grid, any nVoxel
    proj = volume_line_integrals(vol, geo)
    ref = c * _chords(geo)
    assert proj.shape == (3, 20, 28)
    assert ref.max() > 1.0 and (ref == 0).any()      # rays that hit and rays that miss
    assert np.abs(proj - ref).max() <= 1e-5 * ref.max()


def test_gaussian_blob_closed_form():
    # f(p) = exp(-|p - c|^2 / (2 s^2)) sampled at 64^3 source voxel centres; its line
    # integral over the box chord [t0, t1] is s sqrt(pi/2) exp(-d^2/(2 s^2))
    # [erf((t1 - tc)/(s sqrt 2)) - erf((t0 - tc)/(s sqrt 2))], d = distance ray-centre,
    # tc = t of the closest point. The voxel object is the trilinear interpolant of the
    # samples, whose error is <= h^2/8 sum |f_ii| ~ 0.2 % of the peak density for h = 1/32,
    # s = 0.35; the stated tolerance is 0.2 % of the largest projection.
    n, s = 64, 0.35
    c = np.array([0.2, -0.1, 0.15])
    x = -1 + (np.arange(n) + 0.5) * 2 / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    vol = np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / (2 * s * s))
    geo = _geo("cone", det=(24, 32), views=4)
    proj = volume_line_integrals(vol.astype(np.float32), geo, oversample=8)

    o, d = geo.pixel_rays_numpy()
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.maximum(np.minimum(ta, tb).max(-1), 0.0)
    t1 = np.maximum(ta, tb).min(-1)
    tc = np.einsum("...k,...k->...", c - o, d)
    dist2 = np.einsum("...k,...k->...", c - o, c - o) - tc ** 2
    r2 = s * math.sqrt(2)
    ref = s * math.sqrt(math.pi / 2) * np.exp(-dist2 / (2 * s * s)) * (
        erf((t1 - tc) / r2) - erf((t0 - tc) / r2))
    ref = np.where(t1 > t0, ref, 0.0)
    err = np.abs(proj - ref).max()
    assert err <= 2e-3 * ref.max(), err / ref.max()
    # and an axis mix-up (a blob moved off-centre in x, y, z differently) would fail:
    proj_swapped = volume_line_integrals(np.ascontiguousarray(
        vol.transpose(1, 0, 2)).astype(np.float32), geo, oversample=8)
    assert np.abs(proj_swapped - ref).max() > 10 * err


def test_step_halving_converges():
    # Stated tolerance: halving the default step (1/4 -> 1/8 source voxel) changes the
    # projections of a worst-case (white-noise) volume by < 2e-3 of their maximum, and the
    # error against a 1/32-voxel reference shrinks with every halving.
    vol = np.random.default_rng(3).random((16, 16, 16)).astype(np.float32)
    geo = _geo("cone", det=(16, 20), views=2)
    p = {k: volume_line_integrals(vol, geo, oversample=k) for k in (2, 4, 8, 32)}
    scale = p[32].max()
    assert np.abs(p[8] - p[4]).max() < 2e-3 * scale
    errs = [np.abs(p[k] - p[32]).max() for k in (2, 4, 8)]
    assert errs[0] > errs[1] > errs[2]


def _trilinear_reference(vol, pts):
    """Clamped trilinear interpolant at points [..., 3] in continuous source-index units
    (centres at integers); scipy's order-1 spline with 'nearest' clamps beyond the edge."""
    return map_coordinates(vol.astype(np.float64), np.moveaxis(pts, -1, 0), order=1,
                           mode="nearest")


@pytest.mark.parametrize("n_out", [(6, 5, 4), (16, 7, 3)])
def test_average_to_grid_matches_brute_force(n_out):
    vol = np.random.default_rng(0).random((12, 10, 8)).astype(np.float32)
    got = average_to_grid(vol, n_out)
    assert got.shape == n_out
    # brute force: mean of the trilinear object over k^3 sub-points of each output voxel
    k = 24
    axes = []
    for a in range(3):
        r = vol.shape[a] / n_out[a]
        j = np.arange(n_out[a])[:, None]
        axes.append(((j + (np.arange(k) + 0.5) / k) * r - 0.5).reshape(-1))
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    dense = _trilinear_reference(vol, P)
    ref = dense.reshape(n_out[0], k, n_out[1], k, n_out[2], k).mean(axis=(1, 3, 5))
    assert np.abs(got - ref).max() < 2e-3


def test_block_average():
    vol = np.random.default_rng(1).random((8, 8, 4)).astype(np.float32)
    got = block_average(vol, (4, 2, 2))
    assert np.allclose(got[1, 0, 1], vol[2:4, 0:4, 2:4].mean(), atol=1e-6)
    with pytest.raises(ValueError, match="divide"):
        block_average(vol, (3, 2, 2))


def test_simulate_volume_case_from_data_dir(tmp_path, monkeypatch):
    x = -1 + (np.arange(20) + 0.5) / 10
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    vol = (X ** 2 + (Y / 0.7) ** 2 + Z ** 2 < 0.6).astype(np.float32) * 0.8
    np.save(tmp_path / "ball_20.npy", vol)
    (tmp_path / "README.md").write_text(
        "| file | what | source | licence |\n|---|---|---|---|\n"
        "| ball_20.npy | a test ball | `made here` | CC0 |\n")
    monkeypatch.setenv(DATA_ENV, str(tmp_path))
    assert data_dir() == tmp_path
    geo = _geo("cone", n=(10, 10, 10), det=(16, 16), views=4)
    case = simulate_volume_case("ball_20.npy", geo, noise=NoiseModel(), seed=2)
    info = case.info
    assert info["volume"]["file"] == "ball_20.npy" and info["volume"]["licence"] == "CC0"
    assert len(info["volume"]["sha256"]) == 64
    assert info["sampling"]["step_in_source_voxels"] == 0.25
    assert case.vol_gt.shape == (10, 10, 10)
    np.testing.assert_allclose(case.vol_gt, average_to_grid(vol, (10, 10, 10)), atol=1e-6)
    exact = volume_line_integrals(vol, geo)
    assert case.train.shape == exact.shape and not np.allclose(case.train, exact)
    # TIGRE noise at I0 = 1e4 is a few percent of the largest line integral
    assert np.abs(case.train - exact).mean() < 0.05 * exact.max()
    np.testing.assert_array_equal(case.test, volume_line_integrals(vol, geo,
                                                                   case.test_angles))
    again = simulate_volume_case(tmp_path / "ball_20.npy", geo, noise=NoiseModel(), seed=2)
    np.testing.assert_array_equal(again.train, case.train)   # seeded


def test_data_dir_errors(monkeypatch, tmp_path):
    monkeypatch.setenv(DATA_ENV, str(tmp_path / "nope"))
    with pytest.raises(FileNotFoundError, match=DATA_ENV):
        data_dir()
    monkeypatch.setenv(DATA_ENV, str(tmp_path))
    with pytest.raises(FileNotFoundError, match="missing.npy"):
        simulate_volume_case("missing.npy", _geo())
    with pytest.raises(ValueError, match="NaN"):
        volume_line_integrals(np.full((4, 4, 4), np.nan, np.float32), _geo())


def test_shared_volume_fits_default_detector():
    # The data volumes fill the cube: the default detector must see the whole shadow, so the
    # outermost detector rows and columns get (almost) nothing.
    try:
        path = data_dir() / "bone_128.npy"
    except FileNotFoundError:
        pytest.skip("no shared data directory")
    if not path.is_file():
        pytest.skip("bone_128.npy not present")
    from mi_grg.data.simulate import default_geometry
    geo = default_geometry(n=16, det=32, views=2)
    proj = volume_line_integrals(path, geo, oversample=1)
    border = np.concatenate([proj[:, 0].ravel(), proj[:, -1].ravel(), proj[:, :, 0].ravel(),
                             proj[:, :, -1].ravel()])
    assert proj.max() > 0.5 and border.max() == 0.0
