"""Joseph forward projector and its exact adjoint (mi_grg.core.joseph).

References: adjoint dot-product test; closed-form chord lengths of a ball and of the volume
box (float64 NumPy); RTK's JosephForwardProjectionImageFilter (itk-rtk, test-only) on the
same geometry. The RTK geometry mapping below is also used by test_fdk.py and the bench.
"""
import numpy as np
import pytest

from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.core import joseph as vp
from mi_grg.core.joseph import back_project, forward_project, forward_project_dr
from mi_grg.core.view_vectors import circular_vectors

# itk's SWIG wrappers emit hundreds of these on import
pytestmark = pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")


# ---------------------------------------------------------------- helpers
def geometry(mode="cone", n=(16, 18, 20), det=(24, 32), views=5, **kw):
    """A small scan with a non-cubic volume and offsets, so no axis can be confused."""
    kw.setdefault("offOrigin", (0.1, -0.05, 0.02))
    kw.setdefault("offDetector", (0.05, -0.1))
    return Geometry(mode=mode, DSD=7.0, DSO=5.0, nDetector=det,
                    sDetector=(3.0, 4.0) if mode == "cone" else (2.6, 3.2), nVoxel=n,
                    sVoxel=(2.0, 2.2, 2.4), angles=circular_angles(views) + 0.3, **kw)


def ball_volume(geo, centre, radius, density=1.0, ss=3):
    """Voxel-averaged indicator of a ball (ss^3 sub-samples per voxel), [x, y, z]."""
    axes = []
    for n, s, o, c in zip(geo.nVoxel, geo.sVoxel, geo.offOrigin, centre):
        d = s / n
        axes.append(-s / 2 + o - c + (np.arange(n * ss) + 0.5) * d / ss)
    occ = ((axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2
            + axes[2][None, None, :] ** 2) <= radius ** 2).astype(np.float64)
    nx, ny, nz = geo.nVoxel
    return density * occ.reshape(nx, ss, ny, ss, nz, ss).mean(axis=(1, 3, 5))


def ball_chords(geo, centre, radius, density=1.0):
    """Closed-form line integrals [view, v, u] of a uniform ball (float64)."""
    o, d = geo.pixel_rays_numpy()
    w = np.asarray(centre) - o
    tc = np.sum(w * d, -1)
    d2 = np.sum(w * w, -1) - tc ** 2
    return density * 2.0 * np.sqrt(np.maximum(radius ** 2 - d2, 0.0))


def box_chords(geo):
    """Closed-form chord lengths [view, v, u] of every pixel ray through the volume box."""
    o, d = geo.pixel_rays_numpy()
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), -1)
    tmax = np.nanmin(np.maximum(t1, t2), -1)
    return np.maximum(tmax - tmin, 0.0)


# ---------------------------------------------------------------- RTK peer (test-only)
def rtk_or_skip():
    """Import itk-rtk (a test-only dependency, ~15 s import) or skip with the reason."""
    try:
        import itk
        from itk import RTK as rtk
        return itk, rtk
    except Exception as exc:  # pragma: no cover - depends on the environment
        pytest.skip(f"itk-rtk is not installed ({exc}); `pip install itk-rtk` to run")


def rtk_geometry(rtk, geo, angles=None):
    """Our Geometry as RTK's ThreeDCircularProjectionGeometry (cone beam).

    RTK rotates the source about +Y: at gantry angle g (degrees) it sits at
    SID (sin g, 0, cos g); detector u along (cos g, 0, -sin g), v along +Y. Our source sits
    at DSO (cos a, sin a, 0) with u along (-sin a, cos a, 0), v along -z. Relabelling our
    world point (x, y, z) as RTK's (X, Y, Z) = (y, -z, x) maps one onto the other with
    g = degrees(a) and the same u, v directions (the relabelling is a reflection, applied
    to volume and detector alike, so every line integral is preserved). A per-view scan
    whose views differ in angle and distances only maps view by view."""
    g = rtk.ThreeDCircularProjectionGeometry.New()
    if geo.per_view and angles is None:
        # per-view rows of the in-plane kind only (each view its own angle, SID and SDD)
        vec = geo.view_vectors()
        a = np.arctan2(vec[:, 1], vec[:, 0])
        sid = np.hypot(vec[:, 0], vec[:, 1])
        back = np.hypot(vec[:, 3], vec[:, 4])       # to the detector centre (offset)
        sdd = sid + np.sqrt(back ** 2 - geo.offDetector[1] ** 2)
        want = np.stack(np.broadcast_arrays(*circular_vectors(
            np.cos(a), np.sin(a), sdd, sid, geo.dDetector, geo.offDetector)), -1)
        assert np.allclose(vec, want, atol=1e-9), "rows beyond RTK's angle, SID and SDD"
        for ang, o, d in zip(a, sid, sdd):
            g.AddProjection(float(o), float(d), float(np.degrees(ang)), 0.0, 0.0)
        return g
    a = geo.angles if angles is None else angles
    for ang in np.asarray(a, np.float64):
        g.AddProjection(geo.DSO, geo.DSD, float(np.degrees(ang)), 0.0, 0.0)
    return g


def to_rtk_volume(itk, vol, geo):
    """Volume [x, y, z] -> ITK image on RTK axes (numpy order [Z, Y, X] = [x, -z, y])."""
    arr = np.ascontiguousarray(np.asarray(vol, np.float32).transpose(0, 2, 1)[:, ::-1, :])
    img = itk.image_from_array(arr)
    xs, ys, zs = geo.voxel_axes()
    img.SetOrigin([float(ys[0]), float(-zs[-1]), float(xs[0])])
    dx, dy, dz = geo.dVoxel
    img.SetSpacing([dy, dz, dx])
    return img


def from_rtk_volume(itk, img):
    """Inverse of ``to_rtk_volume``: ITK image -> [x, y, z]."""
    arr = itk.array_from_image(img)
    return np.ascontiguousarray(arr[:, ::-1, :].transpose(0, 2, 1))


def to_rtk_projections(itk, proj, geo):
    """Projections [view, v, u] -> ITK stack (numpy order is the same); pixel centres and
    offDetector go into the origin, so the principal ray stays at detector (0, 0)."""
    img = itk.image_from_array(np.ascontiguousarray(proj, np.float32))
    nv, nu = geo.nDetector
    dv, du = geo.dDetector
    img.SetOrigin([(0.5 - nu / 2) * du + geo.offDetector[1],
                   (0.5 - nv / 2) * dv + geo.offDetector[0], 0.0])
    img.SetSpacing([du, dv, 1.0])
    return img


def rtk_forward(itk, rtk, vol, geo):
    IF3 = itk.Image[itk.F, 3]
    f = rtk.JosephForwardProjectionImageFilter[IF3, IF3].New()
    f.SetInput(0, to_rtk_projections(itk, np.zeros(geo.projection_shape, np.float32), geo))
    f.SetInput(1, to_rtk_volume(itk, vol, geo))
    f.SetGeometry(rtk_geometry(rtk, geo))
    f.Update()
    return np.array(itk.array_from_image(f.GetOutput()), copy=True)


def rtk_fdk(itk, rtk, proj, geo, weighting=None):
    """RTK's FDK of projections [view, v, u] (truncation correction off) -> [x, y, z];
    ``weighting``: the name of an RTK redundancy filter applied first
    ("DisplacedDetectorImageFilter", "ParkerShortScanImageFilter") or None."""
    IF3 = itk.Image[itk.F, 3]
    g = rtk_geometry(rtk, geo)
    p = to_rtk_projections(itk, proj, geo)
    if weighting is not None:
        w = getattr(rtk, weighting)[IF3].New()
        w.SetInput(p)
        w.SetGeometry(g)
        p = w.GetOutput()
    f = rtk.FDKConeBeamReconstructionFilter[IF3].New()
    f.SetInput(0, to_rtk_volume(itk, np.zeros(geo.nVoxel, np.float32), geo))
    f.SetInput(1, p)
    f.SetGeometry(g)
    f.GetRampFilter().SetTruncationCorrection(0.0)
    f.Update()
    return from_rtk_volume(itk, f.GetOutput())


# ---------------------------------------------------------------- tests
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_adjoint_dot_product(variant, mode, rng):
    geo = geometry(mode)
    x = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    y = rng.uniform(0, 1, geo.projection_shape).astype(np.float32)
    Ax, Aty = forward_project(x, geo), back_project(y, geo)
    lhs = np.dot(Ax.ravel().astype(np.float64), y.ravel())
    rhs = np.dot(x.ravel().astype(np.float64), Aty.ravel())
    assert lhs > 1.0                                   # rays do hit the volume
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


def test_chunked_views_give_the_same_result(monkeypatch, rng):
    geo = geometry("cone")
    x = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    y = rng.uniform(0, 1, geo.projection_shape).astype(np.float32)
    whole_f, whole_b = forward_project(x, geo), back_project(y, geo)
    monkeypatch.setattr(vp, "MAX_RAYS", 2 * geo.nDetector[0] * geo.nDetector[1])  # 2 views
    np.testing.assert_allclose(forward_project(x, geo), whole_f, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(back_project(y, geo), whole_b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_ball_matches_closed_form_chords_and_error_falls_with_refinement(mode):
    centre, radius, rho = (0.1, -0.2, 0.15), 0.6, 1.5
    errors = []
    for n in (16, 32, 64):
        geo = geometry(mode, n=(n, n, n), det=(40, 40), views=3, offOrigin=(0, 0, 0))
        p = forward_project(ball_volume(geo, centre, radius, rho), geo)
        ref = ball_chords(geo, centre, radius, rho)
        errors.append(np.mean(np.abs(p - ref)) / ref.max())
    # first-order discretisation error: each halving of the voxel at least 1.5x smaller
    assert errors[1] < errors[0] / 1.5 and errors[2] < errors[1] / 1.5, errors
    assert errors[2] < 3e-3, errors


def test_uniform_box_matches_closed_form_chords():
    errors = []
    for n in (16, 32, 64):
        geo = geometry("cone", n=(n, n, n), det=(32, 32), views=3)
        p = forward_project(np.ones(geo.nVoxel, np.float32), geo)
        ref = box_chords(geo)
        assert p.max() == pytest.approx(ref.max(), rel=0.05)
        errors.append(np.mean(np.abs(p - ref)) / ref.max())
    assert errors[1] < errors[0] / 1.5 and errors[2] < errors[1] / 1.5, errors


def test_dr_variant_returns_a_tensor():
    import mitsuba as mi
    geo = geometry("parallel")
    x = np.ones(geo.nVoxel, np.float32)
    t = forward_project_dr(mi.TensorXf(x), geo, angles=[0.0, 1.0])
    assert isinstance(t, mi.TensorXf) and tuple(t.shape) == (2, *geo.nDetector)
    np.testing.assert_allclose(t.numpy(), forward_project(x, geo, [0.0, 1.0]), rtol=1e-6)


def test_bad_inputs_are_named():
    geo = geometry("cone")
    with pytest.raises(ValueError, match=r"\[x, y, z\] = nVoxel = \(16, 18, 20\)"):
        forward_project(np.zeros((16, 18, 19)), geo)
    bad = np.zeros(geo.nVoxel)
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        forward_project(bad, geo)
    with pytest.raises(ValueError, match=r"\[view, v, u\].*\(5, 24, 32\)"):
        back_project(np.zeros((4, 24, 32)), geo)
    with pytest.raises(ValueError, match=r"\(2, 24, 32\)"):
        back_project(np.zeros((5, 24, 32)), geo, angles=[0.0, 1.0])
    p = np.zeros(geo.projection_shape)
    p[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        back_project(p, geo)
    with pytest.raises(ValueError, match="no views"):
        forward_project(np.zeros(geo.nVoxel), geo, angles=[])


def test_forward_projection_agrees_with_rtk_joseph():
    """RTK's Joseph projector uses the same interpolation (bilinear on the planes of the
    dominant axis), so the two agree to float32 rounding, not merely to the discretisation
    error (which is ~8 % here against the exact projections of the thin-skulled phantom)."""
    itk, rtk = rtk_or_skip()
    from mi_grg.data.phantoms import make_phantom
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=circular_angles(7) + 0.1)
    vol = make_phantom("shepp").voxelize(geo, 2)
    ours = forward_project(vol, geo)
    ref = rtk_forward(itk, rtk, vol, geo)
    assert np.linalg.norm(ref) > 1.0
    assert np.linalg.norm(ours - ref) <= 1e-4 * np.linalg.norm(ref)
    assert np.abs(ours - ref).max() <= 1e-4 * ref.max()
