"""FDK / FBP (mi_grg.classical.fdk).

References: density of a uniform ball from its closed-form projections (units), the
analytic ramp |f|, scikit-image's ``iradon`` (2-D parallel-beam peer), RTK's
FDKConeBeamReconstructionFilter (3-D cone-beam peer, itk-rtk test-only), and PSNR against
the voxelised Shepp-Logan phantom as the number of views grows.
"""
import numpy as np
import pytest

from mi_grg.data.case import Case
from mi_grg.classical.fdk import reconstruct_fdk
from mi_grg.core.fdk import FILTERS, fdk, ramp_filter
from mi_grg.core.geometry import Geometry, circular_angles

from test_voxel_projector import ball_chords, ball_volume, rtk_fdk, rtk_or_skip

pytestmark = pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")


def ball_case(mode, n=40, views=120):
    # offsets on volume and detector, so that a sign slip in either would show
    geo = Geometry(mode=mode, DSD=7.0, DSO=5.0, nDetector=(56, 56),
                   sDetector=(3.0, 3.0) if mode == "cone" else (2.2, 2.2), nVoxel=(n, n, n),
                   sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(views),
                   offOrigin=(0.05, -0.04, 0.03), offDetector=(0.06, -0.08))
    centre, radius, rho = np.array([0.1, -0.2, 0.1]), 0.5, 2.0
    X, Y, Z = np.meshgrid(*geo.voxel_axes(), indexing="ij")
    r = np.sqrt((X - centre[0]) ** 2 + (Y - centre[1]) ** 2 + (Z - centre[2]) ** 2)
    return geo, ball_chords(geo, centre, radius, rho).astype(np.float32), r, rho


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_ball_density_is_recovered_in_ground_truth_units(variant, mode):
    geo, proj, r, rho = ball_case(mode)
    vol = fdk(proj, geo)
    assert vol.dtype == np.float32 and vol.shape == geo.nVoxel
    inner, outer = vol[r < 0.35], vol[r > 0.65]
    assert inner.mean() == pytest.approx(rho, rel=0.01)
    assert inner.std() < 0.02 * rho
    assert np.abs(outer).mean() < 0.01 * rho
    # whole-volume error against the voxelised ball: 0.007-0.008 rho here; a detector
    # offset applied with the wrong sign gives >= 0.024 rho
    ref = ball_volume(geo, (0.1, -0.2, 0.1), 0.5, rho)
    assert np.abs(vol - ref).mean() < 0.015 * rho


def test_ramp_response_is_the_band_limited_ramp():
    """The DFT of the spatial kernel approximates |f| (cycles per sample) and keeps a
    small positive DC term instead of 0 (Kak & Slaney's point)."""
    H = ramp_filter(100)
    L = H.size
    assert L == 256                                  # >= 2 x 100, power of two
    f = np.abs(np.fft.fftfreq(L))
    assert 0 < H[0] < 1.0 / L
    mid = (f > 0.02) & (f < 0.45)
    np.testing.assert_allclose(H[mid], f[mid], rtol=0.02)
    for name in FILTERS[1:]:                         # windows only attenuate
        assert np.all(ramp_filter(100, name) <= H + 1e-12)
    with pytest.raises(ValueError, match="ram-lak"):
        ramp_filter(100, "hamming")


# ---------------------------------------------------------------- scikit-image (2-D)
def skimage_slice_case(n=65, views=60):
    """A 2-D Shepp-Logan slice, its skimage sinogram and our matching one-slice geometry.

    Mapping (derived once): our volume [x, y] = image [row, col]; skimage's angle theta
    (degrees) equals our angle a (radians -> degrees), same rotation sense; its detector
    bin s runs along our u. n is odd so that skimage's centre index n // 2 is the geometric
    centre (n - 1) / 2 of our pixel grid. Unit pixels, parallel beam, one detector row
    through the single voxel slice."""
    from skimage.data import shepp_logan_phantom
    from skimage.transform import radon, resize
    img = resize(shepp_logan_phantom(), (n, n), anti_aliasing=True)
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    img[xx ** 2 + yy ** 2 > ((n - 1) / 2) ** 2] = 0
    theta = np.arange(views) * 180.0 / views
    sino = radon(img, theta=theta, circle=True)                  # [s, view]
    geo = Geometry(mode="parallel", DSD=3.0 * n, DSO=2.0 * n, nDetector=(1, n),
                   sDetector=(1.0, n), nVoxel=(n, n, 1), sVoxel=(n, n, 1.0),
                   angles=np.radians(theta))
    proj = np.ascontiguousarray(sino.T[:, None, :], dtype=np.float32)
    inside = (xx ** 2 + yy ** 2) < ((n - 1) / 2 - 2) ** 2
    return img, theta, sino, geo, proj, inside


@pytest.mark.parametrize("ours,theirs,tol", [
    ("ram-lak", "ramp", 1e-5), ("shepp-logan", "shepp-logan", 1e-5),
    ("cosine", "cosine", 1e-5),
    # skimage's Hann is np.hanning(n) (symmetric, n points) where ours is the periodic
    # 0.5 (1 + cos 2 pi f): ~1e-3 apart
    ("hann", "hann", 3e-3)])
def test_fbp_matches_skimage_iradon(ours, theirs, tol):
    """Both build the ramp in the spatial domain, pad to max(64, 2^ceil(log2 2n)), sample
    linearly and scale by pi / n_views: they agree to float32 rounding."""
    from skimage.transform import iradon
    img, theta, sino, geo, proj, inside = skimage_slice_case()
    ref = iradon(sino, theta=theta, filter_name=theirs, circle=True)
    vol = fdk(proj, geo, filter=ours)[:, :, 0]
    err = np.linalg.norm((vol - ref)[inside]) / np.linalg.norm(ref[inside])
    assert err < tol, err


# ---------------------------------------------------------------- RTK (3-D cone beam)
def test_fdk_matches_rtk():
    """Same cosine weights, spatial-domain ramp, zero padding, bilinear voxel-driven
    back-projection with (DSO / (DSO - s))^2 and angular weights: agreement to float32
    rounding (RTK's truncation correction is switched off)."""
    itk, rtk = rtk_or_skip()
    from mi_grg.data.phantoms import make_phantom
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=circular_angles(40))
    proj = make_phantom("shepp").line_integrals(geo).astype(np.float32)
    ref = rtk_fdk(itk, rtk, proj, geo)
    ours = fdk(proj, geo)
    assert np.linalg.norm(ref) > 1.0
    assert np.linalg.norm(ours - ref) <= 1e-4 * np.linalg.norm(ref)


# ---------------------------------------------------------------- convergence
def test_psnr_rises_with_the_number_of_views():
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.data.simulate import default_geometry
    ph = make_phantom("shepp")
    gt = ph.voxelize(default_geometry(48, 64, 25), 2)
    psnr = []
    for views in (25, 50, 100, 200):
        geo = default_geometry(48, 64, views)
        psnr.append(psnr_3d(fdk(ph.line_integrals(geo).astype(np.float32), geo), gt))
    assert all(b > a for a, b in zip(psnr, psnr[1:])), psnr
    assert psnr[-1] - psnr[0] > 3.0, psnr


# ---------------------------------------------------------------- contract and errors
def test_reconstruct_fdk_contract(small_cone_geometry, rng):
    geo = small_cone_geometry
    case = Case(geometry=geo, train=rng.uniform(0, 1, geo.projection_shape).astype(np.float32))
    vol = reconstruct_fdk(case, filter="hann")
    assert vol.dtype == np.float32 and vol.shape == geo.nVoxel and np.all(np.isfinite(vol))
    with pytest.raises(TypeError, match="window"):
        reconstruct_fdk(case, window="hann")
    with pytest.raises(ValueError, match="filter must be one of"):
        reconstruct_fdk(case, filter="ramp")


def test_bad_projections_are_rejected(small_cone_geometry):
    geo = small_cone_geometry
    with pytest.raises(ValueError, match=r"\[view, v, u\]"):
        fdk(np.zeros((geo.n_views, 24, 31)), geo)
    p = np.zeros(geo.projection_shape)
    p[2, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fdk(p, geo)
    with pytest.raises(ValueError, match="no views"):
        fdk(np.zeros((0, 24, 32)), geo, angles=[])
