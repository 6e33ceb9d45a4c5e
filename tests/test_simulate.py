"""Simulated cases: default scanner covers the volume's shadow, splits, noise, metadata."""
import numpy as np
import pytest

import mi_grg  # noqa: F401
from mi_grg.data.case import Case
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.noise import NoiseModel
from mi_grg.data.phantoms import make_phantom
from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case


def corners_on_detector(geo: Geometry) -> bool:
    """Whether every voxel corner of the volume box projects onto the detector at every
    angle (projected by hand: central projection from the source onto the detector plane,
    or orthogonal projection in parallel beam)."""
    edges = [o - s / 2 + np.arange(n + 1) * (s / n)
             for n, s, o in zip(geo.nVoxel, geo.sVoxel, geo.offOrigin)]
    X = np.stack(np.meshgrid(*edges, indexing="ij"), -1).reshape(-1, 3)
    f = geo.detector_frame()
    half_v, half_u = geo.sDetector[0] / 2, geo.sDetector[1] / 2
    for k in range(geo.n_views):
        src, ctr, nrm = f["source"][k], f["center"][k], f["normal"][k]
        if geo.mode == "cone":
            t = ((ctr - src) @ nrm) / ((X - src) @ nrm)
            hit = src + t[:, None] * (X - src)
        else:
            hit = X
        u, v = (hit - ctr) @ f["e_u"][k], (hit - ctr) @ f["e_v"][k]
        if np.abs(u).max() >= half_u or np.abs(v).max() >= half_v:
            return False
    return True


def test_default_geometry_fields():
    g = default_geometry()
    assert (g.mode, g.DSD, g.DSO, g.sVoxel) == ("cone", 7.0, 5.0, (2.0, 2.0, 2.0))
    assert g.nVoxel == (64, 64, 64) and g.nDetector == (96, 96) and g.n_views == 25
    np.testing.assert_array_equal(g.angles, circular_angles(25))
    assert g.angles.max() < 2 * np.pi
    p = default_geometry(n=32, det=40, views=7, mode="parallel")
    assert p.mode == "parallel" and p.nVoxel == (32, 32, 32) and p.n_views == 7
    with pytest.raises(ValueError, match="mode"):
        default_geometry(mode="fan")


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_detector_covers_every_voxel_corner(mode):
    g = default_geometry(mode=mode)
    assert corners_on_detector(g)
    # the box is convex, so a coarser corner grid suffices for a dense set of angles
    dense = g.replace(nVoxel=(4, 4, 4), angles=np.linspace(0, 2 * np.pi, 720))
    assert corners_on_detector(dense)
    # Negative control: R2-Gaussian's own detector sizes (4.0 cone, 2.0 parallel) miss corners.
    r2 = {"cone": 4.0, "parallel": 2.0}[mode]
    assert not corners_on_detector(dense.replace(sDetector=(r2, r2)))


def test_default_test_angles_lie_between_training_angles():
    train = circular_angles(8)
    test = default_test_angles(8)
    np.testing.assert_allclose(test, train + np.pi / 8)
    np.testing.assert_allclose(test - train, (train[1] - train[0]) / 2)
    assert np.all(np.abs(test[:, None] - train[None]).min(1) > 0.3)


def small_geometry(mode="cone"):
    return default_geometry(n=16, det=24, views=5, mode=mode)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_noise_free_case_is_exact(mode):
    geo = small_geometry(mode)
    case = simulate_case("shepp", geo, noise=None, supersample=2)
    ph = make_phantom("shepp")
    assert isinstance(case, Case) and case.scene_scale == 1.0
    assert case.train.dtype == np.float32 and case.train.shape == (5, 24, 24)
    np.testing.assert_array_equal(case.train, ph.line_integrals(geo).astype(np.float32))
    np.testing.assert_array_equal(case.test_angles, default_test_angles(5))
    np.testing.assert_array_equal(case.test, ph.line_integrals(geo, case.test_angles)
                                  .astype(np.float32))
    np.testing.assert_array_equal(case.vol_gt, ph.voxelize(geo, supersample=2))
    assert case.vol_gt.shape == (16, 16, 16) and case.vol_gt.dtype == np.float32
    assert case.geometry is geo
    assert case.info == {"source": "mi_grg.data.simulate", "phantom": "shepp", "n_ellipsoids": 10,
                         "noise": None, "seed": 0, "supersample": 2, "mode": mode,
                         "n_voxel": [16, 16, 16], "n_detector": [24, 24], "n_train": 5,
                         "n_test": 5, "noise_seed": 0}


def test_noise_only_on_training_views_and_reproducible():
    geo = small_geometry()
    noise = NoiseModel()
    a = simulate_case("needles", geo, [0.1, 0.2, 0.3], noise, seed=2, supersample=1)
    b = simulate_case("needles", geo, [0.1, 0.2, 0.3], noise, seed=2, supersample=1)
    c = simulate_case("needles", geo, [0.1, 0.2, 0.3], noise, seed=3, supersample=1)
    ph = make_phantom("needles", seed=2)
    exact = ph.line_integrals(geo)
    assert np.array_equal(a.train, b.train) and not np.array_equal(a.train, c.train)
    diff = a.train - exact
    assert np.abs(diff).max() > 1e-3                          # noise is there
    body = exact > 0.1 * exact.max()    # away from 0, where negatives are clipped (biased)
    assert abs(diff[body].mean()) < 0.1 * diff[body].std()    # roughly unbiased
    np.testing.assert_array_equal(a.test, ph.line_integrals(geo, [0.1, 0.2, 0.3])
                                  .astype(np.float32))        # test views exact
    np.testing.assert_array_equal(a.vol_gt, ph.voxelize(geo, supersample=1))
    assert a.info["noise"] == noise.to_dict() and a.info["seed"] == 2
    assert a.info["phantom"] == "needles" and a.info["n_test"] == 3


def test_phantom_instance_and_empty_test_split():
    geo = small_geometry()
    ph = make_phantom("shells", seed=5)
    case = simulate_case(ph, geo, test_angles=[], supersample=1)
    assert case.test.shape == (0, 24, 24) and case.info["n_test"] == 0
    assert case.info["phantom"] == "shells"
    np.testing.assert_array_equal(case.train, ph.line_integrals(geo).astype(np.float32))


def test_invalid_arguments():
    geo = small_geometry()
    with pytest.raises(ValueError, match="shepp, needles, shells, blobs"):
        simulate_case("walnut", geo)
    with pytest.raises(TypeError, match="noise"):
        simulate_case("shepp", geo, noise={"I0": 1e4})
    with pytest.raises(TypeError, match="geometry"):
        simulate_case("shepp", geo.to_scanner_dict())
    with pytest.raises(TypeError, match="phantom"):
        simulate_case(3, geo)
    with pytest.raises(ValueError, match="test_angles"):
        simulate_case("shepp", geo, test_angles=[np.nan])
