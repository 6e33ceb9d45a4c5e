"""Per-view scan geometry (Geometry.vectors, mi_grg.core.view_vectors) in every forward model.

References are independent of the implementation: the rays are built here from the 12
numbers of each view with ASTRA's pixel formula (float64), the circular rows from the
conventions of docs/conventions.md written out by hand; closed-form line integrals of
Gaussians and of a ball on those rays; the adjoint dot-product identity; and the traced
training step for the recorded one.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_grg  # noqa: F401  (first: Dr.Jit's LLVM library and the variant)
from mi_grg.core.geometry import Geometry, GeometryError, circular_angles
from mi_grg.core.joseph import back_project, forward_project
from mi_grg.core.projector import project
from mi_grg.data.orbits import half_fan, wobbling
from test_recording import one_thread  # noqa: F401  (fixture: one Dr.Jit thread)
from test_projector import as_arrays, plane_gradients, quat_matrix, random_gaussians


def scan(mode="cone", views=6, **kw):
    return Geometry(mode=mode, DSD=7.0, DSO=5.0, nDetector=(20, 28), sDetector=(3.0, 4.0),
                    nVoxel=(12, 14, 16), sVoxel=(2.0, 2.0, 2.2),
                    angles=circular_angles(views) + 0.2, **kw)


def astra_rays(geo):
    """Float64 pixel-centre rays [view, v, u, 3] from each view's 12 numbers (ASTRA:
    pixel (i, j) at d + (j + 0.5 - nU/2) u + (i + 0.5 - nV/2) v)."""
    vec = geo.view_vectors()
    nv, nu = geo.nDetector
    j = np.arange(nu) + 0.5 - nu / 2
    i = np.arange(nv) + 0.5 - nv / 2
    pix = (vec[:, None, None, 3:6] + j[None, None, :, None] * vec[:, None, None, 6:9]
           + i[None, :, None, None] * vec[:, None, None, 9:12])
    if geo.mode == "cone":
        src = np.broadcast_to(vec[:, None, None, 0:3], pix.shape)
        d = pix - src
        return src, d / np.linalg.norm(d, axis=-1, keepdims=True)
    d = np.broadcast_to(vec[:, None, None, 0:3] / np.linalg.norm(vec[:, 0:3], axis=1)[:, None, None, None],
                        pix.shape)
    return pix - 50.0 * d, d


def gaussian_reference(geo, pos, scales, rots, rho, half=False):
    """Whole-line integrals of the Gaussians on ``astra_rays`` (closed form); ``half``:
    cone-beam rays start at the source."""
    from scipy.special import ndtr
    o, d = astra_rays(geo)
    R = quat_matrix(rots)
    A = np.einsum("nij,nj,nkj->nik", R, 1.0 / np.asarray(scales) ** 2, R)
    out = np.zeros(o.shape[:-1])
    for k in range(len(rho)):
        w = o - pos[k]
        a = np.einsum("...i,ij,...j->...", d, A[k], d)
        b = np.einsum("...i,ij,...j->...", d, A[k], w)
        c = np.einsum("...i,ij,...j->...", w, A[k], w)
        f = ndtr(-b / np.sqrt(a)) if half else 1.0
        out += rho[k] * np.sqrt(2 * np.pi / a) * np.exp(-0.5 * (c - b * b / a)) * f
    return out


# ---------------------------------------------------------------- the geometry type
def test_circular_rows_follow_the_conventions():
    geo = scan(offDetector=(0.1, -0.3))
    a = geo.angles
    n = np.stack([np.cos(a), np.sin(a), 0 * a], 1)
    e_u = np.stack([-np.sin(a), np.cos(a), 0 * a], 1)
    e_v = np.tile([0.0, 0.0, -1.0], (a.size, 1))
    dv, du = 3.0 / 20, 4.0 / 28
    expect = np.concatenate([5.0 * n, -2.0 * n + 0.1 * e_v - 0.3 * e_u, du * e_u, dv * e_v], 1)
    np.testing.assert_allclose(geo.view_vectors(), expect, rtol=0, atol=1e-15)
    # the circular rays and those of ASTRA's formula on the rows are the same rays
    o, d = geo.pixel_rays_numpy()
    o2, d2 = astra_rays(geo)
    np.testing.assert_allclose(d, d2, atol=1e-14)
    np.testing.assert_allclose(o, o2, atol=1e-14)


def test_subsets_keep_their_vectors_and_scaling():
    w = wobbling(scan())
    sub = w.with_angles(w.angles[[4, 1]])
    np.testing.assert_array_equal(sub.view_vectors(), w.vectors[[4, 1]])
    s = w.scaled(0.5)
    np.testing.assert_allclose(s.view_vectors(), 0.5 * w.view_vectors())
    with pytest.raises(GeometryError, match="view 0: angle .* has no per-view vector"):
        w.with_angles([0.123])
    assert not w.circular().per_view and w.as_vectors().per_view


@pytest.mark.parametrize("change, message", [
    (lambda r: r[:11], "view 3: vector must be 12 finite numbers"),
    (lambda r: np.where(np.arange(12) == 5, np.nan, r), "view 3: vector must be 12 finite"),
    (lambda r: np.concatenate([r[:6], r[6:9], 2 * r[6:9]]), "view 3: detector steps u and v are zero or parallel"),
    (lambda r: np.concatenate([r[:6], 0 * r[6:9], r[9:]]), "view 3: detector steps u and v"),
    (lambda r: np.concatenate([r[3:6] + r[6:9] * 3, r[3:]]), "view 3: the source .* lies on the detector plane"),
    (lambda r: np.concatenate([r[:3], r[3:6] + [0, 0, 40.0], r[6:]]),
     "view 3: the detector does not see the volume"),
])
def test_bad_vectors_name_the_view(change, message):
    geo = scan()
    rows = [list(r) for r in geo.view_vectors()]
    rows[3] = list(change(geo.view_vectors()[3]))
    with pytest.raises(GeometryError, match=message):
        geo.replace(vectors=rows)


def test_conflicting_rows_of_one_angle_are_rejected():
    geo = scan(views=4)
    vec = geo.view_vectors()
    vec[2, 2] += 0.1
    with pytest.raises(GeometryError, match="view 2: its angle .* also that of view 0"):
        geo.replace(vectors=vec, vector_angles=[geo.angles[0], geo.angles[1],
                                                geo.angles[0], geo.angles[3]])


# ---------------------------------------------------------------- forward models
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_gaussian_projector_on_a_wobbling_orbit(mode, rng):
    geo = wobbling(scan(mode), height=0.12, roll_deg=2.0, dsd=0.03)
    g = random_gaussians(rng, 12)
    ref = gaussian_reference(geo, *as_arrays(g))
    got = project(g, geo, extent=9.0)
    assert np.abs(got - ref).max() <= 2e-5 * np.abs(ref).max()
    # and the ignored vectors are visibly different rays
    assert np.abs(project(g, geo.circular(), extent=9.0) - ref).max() > 1e-2 * np.abs(ref).max()


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_gaussian_projector_on_a_skewed_detector(mode, rng):
    """ASTRA's rows allow any u and v: a pixel grid whose rows are sheared against its
    columns (up to 10 degrees, varying per view), against the closed form on ASTRA's rays;
    in cone beam with Gaussians beside and straddling the source (half-line records)."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.view_frames import view_frames
    geo = wobbling(scan(mode), skew_deg=10.0)
    fr = view_frames(geo)
    assert fr.skewed and not fr.shared and np.abs(fr.sk).max() > 0.1 * np.max(fr.dv)
    g = random_gaussians(rng, 12)
    arr = as_arrays(g)
    if mode == "cone":      # two near-source records
        src = geo.view_vectors()[0, 0:3]
        arr[0][:2] = [0.93 * src + [0, 0.05, 0.02], 0.6 * src]
        arr[1][:2] = [[0.5, 0.2, 0.3], [0.3, 0.3, 0.2]]
        g = Gaussians.from_numpy(*arr)
    ref = gaussian_reference(geo, *arr, half=mode == "cone")
    got = project(g, geo, extent=9.0)
    assert np.abs(got - ref).max() <= 2e-5 * np.abs(ref).max()
    # the same scan with its rows at right angles is visibly different
    square = wobbling(scan(mode))
    assert np.abs(project(g, square, extent=9.0) - ref).max() > 1e-2 * np.abs(ref).max()


def test_detector_plane_gradient_on_a_skewed_detector():
    """means2d moves a Gaussian by steps of the sheared pixel lattice: its gradient is
    the 3-D position gradient along that view's u and v steps, scaled to the Gaussian's
    depth (the chain rule through the view's own rows)."""
    geo = wobbling(scan("cone", views=2), height=0.0, roll_deg=0.0, dsd=0.0, skew_deg=12.0)
    y = np.random.default_rng(4).normal(size=(2, *geo.nDetector))
    gmd, gp, g = plane_gradients(geo, y)
    pos = as_arrays(g)[0][0]
    vec = geo.view_vectors()
    for k in range(2):
        s, d, U, V = vec[k, 0:3], vec[k, 3:6], vec[k, 6:9], vec[k, 9:12]
        n = np.cross(U, V)
        scale = np.dot(pos - s, n) / np.dot(d - s, n)
        assert abs(np.dot(U, V)) > 0.1 * np.linalg.norm(U) * np.linalg.norm(V)
        np.testing.assert_allclose(gmd[k], [gp[k] @ U * scale, gp[k] @ V * scale],
                                   rtol=1e-4, atol=1e-6)
    assert np.abs(gmd).min() > 1e-3


def test_joseph_on_a_wobbling_orbit_matches_ball_chords():
    geo = wobbling(Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(20, 28),
                            sDetector=(3.0, 4.0), nVoxel=(40, 40, 44), sVoxel=(2.0, 2.0, 2.2),
                            angles=circular_angles(6) + 0.2))
    centre, radius = np.array([0.1, -0.15, 0.05]), 0.6
    axes = [(-s / 2 + (np.arange(n * 3) + 0.5) * s / n / 3) for n, s in zip(geo.nVoxel, geo.sVoxel)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    occ = ((X - centre[0]) ** 2 + (Y - centre[1]) ** 2 + (Z - centre[2]) ** 2 <= radius ** 2)
    vol = occ.reshape(40, 3, 40, 3, 44, 3).mean(axis=(1, 3, 5))
    o, d = astra_rays(geo)
    w = centre - o
    tc = np.sum(w * d, -1)
    chord = 2 * np.sqrt(np.maximum(radius ** 2 - (np.sum(w * w, -1) - tc ** 2), 0))
    got = forward_project(vol, geo)
    inner = chord > 0.3          # away from the rim, where voxelisation decides
    assert np.abs(got - chord)[inner].mean() < 0.01 * chord.max()
    assert np.abs(forward_project(vol, geo.circular()) - chord)[inner].mean() > \
        3 * np.abs(got - chord)[inner].mean()


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_joseph_adjoint_on_vectors(mode, rng):
    geo = wobbling(scan(mode))
    x = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    y = rng.uniform(0, 1, geo.projection_shape).astype(np.float32)
    lhs = float(np.sum(forward_project(x, geo).astype(np.float64) * y))
    rhs = float(np.sum(x.astype(np.float64) * back_project(y, geo)))
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_circular_scan_given_as_vectors_projects_bit_for_bit(mode, rng, one_thread):
    """(One thread: float atomics then add in one order.)"""
    geo = scan(mode, offDetector=(0.05, 0.2))
    vgeo = geo.as_vectors()
    g = random_gaussians(rng, 30)
    np.testing.assert_array_equal(project(g, geo), project(g, vgeo))
    vol = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    np.testing.assert_array_equal(forward_project(vol, geo), forward_project(vol, vgeo))
    y = rng.uniform(0, 1, geo.projection_shape).astype(np.float32)
    np.testing.assert_array_equal(back_project(y, geo), back_project(y, vgeo))


def test_half_fan_is_an_offset_circular_scan():
    geo = half_fan(scan(), 0.3)
    assert geo.offDetector[1] == pytest.approx(0.3 * 4.0) and not geo.per_view


def test_voxelizer_bounds_follow_the_volume_box(rng):
    """The voxel grid is the volume's box, which per-view vectors leave unchanged."""
    from mi_grg.core.voxelizer import voxelize
    geo = scan()
    g = random_gaussians(rng, 10)
    np.testing.assert_array_equal(voxelize(g, geo), voxelize(g, wobbling(geo)))


# ---------------------------------------------------------------- training
@pytest.mark.parametrize("skew_deg", [0.0, 10.0])
def test_frozen_step_on_a_wobbling_orbit_equals_traced(one_thread, skew_deg):
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    from test_recording import _assert_equal, _frozen_calls, _state
    base = default_geometry(n=16, det=24, views=6)
    test = default_test_angles(2)
    allv = wobbling(base.with_angles(np.concatenate([base.angles, test])), skew_deg=skew_deg)
    case = simulate_case("shepp", allv.with_angles(base.angles), test, NoiseModel(), seed=3)
    tr, raw, fz, said = _state(case)
    fz.per_gaussian.update(rows=40.0, near=0.01)    # room from the first call on
    results = _frozen_calls(tr, raw, fz, [(0, None), (3, None), (1, None), (3, None)])
    assert all(r[2] is not None for r in results), said
    assert fz.n_recordings == 1          # one recording serves every view's own detector
    _assert_equal(tr, raw, results)


@pytest.mark.parametrize("skew_deg", [0.0, 10.0])
def test_traced_step_on_a_wobbling_orbit_reads_each_views_detector(one_thread, skew_deg):
    """The traced step (step.loss_and_grads on one view's inputs) equals the projection
    of that view alone (project_dr); only a per-view scan carries detector inputs (a
    skewed one its shear too, in every view's kernels)."""
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    from mi_grg.training.step import loss_and_grads, view_arrays
    from test_recording import _state, _traced
    base = default_geometry(n=16, det=24, views=6)
    assert "det" not in view_arrays(base, 2)
    allv = wobbling(base.with_angles(np.concatenate([base.angles, default_test_angles(2)])),
                    skew_deg=skew_deg)
    case = simulate_case("shepp", allv.with_angles(base.angles), default_test_angles(2),
                         NoiseModel(), seed=3)
    tr, raw, _, _ = _state(case)
    for view in (1, 4):
        out = loss_and_grads(tr.step_cfg, tr._step_inputs(raw, view))
        got = {k: np.asarray(v) for k, v in out.grads.items()}
        for v in raw.values():
            dr.clear_grad(v)
        ref_loss, ref = _traced(tr, raw, view)
        assert float(out.loss[0]) == pytest.approx(ref_loss, rel=1e-6)
        for k, g in ref.items():
            assert np.abs(got[k] - g).max() <= 1e-5 * np.abs(g).max(), (view, k)


# ---------------------------------------------------------------- in and out
def _wobbling_case(views=6, tests=3):
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    base = default_geometry(n=16, det=24, views=views)
    test = default_test_angles(tests)
    allv = wobbling(base.with_angles(np.concatenate([base.angles, test])))
    return simulate_case("shepp", allv.with_angles(base.angles), test, NoiseModel(), seed=3), allv


def test_save_and_load_keep_the_vectors(tmp_path):
    import json
    import mi_grg as m
    case, allv = _wobbling_case()
    m.save_case(case, tmp_path / "c")
    meta = json.loads((tmp_path / "c" / "meta_data.json").read_text())
    entry = meta["proj_test"][1]
    np.testing.assert_array_equal(entry["vector"], allv.view_vectors([entry["angle"]])[0])
    back = m.load_case(tmp_path / "c", rescale=False)
    np.testing.assert_array_equal(back.geometry.view_vectors(), case.geometry.view_vectors())
    np.testing.assert_array_equal(back.test_geometry.view_vectors(),
                                  case.test_geometry.view_vectors())
    # a mix of entries with and without vectors, and a bad row, are one-line errors
    del meta["proj_test"][1]["vector"]
    (tmp_path / "c" / "meta_data.json").write_text(json.dumps(meta))
    with pytest.raises(m.data.dataset.DatasetError, match=r"proj_train\[0\] has a \"vector\" "
                       r"but proj_test\[1\] has none"):
        m.load_case(tmp_path / "c")
    meta["proj_test"][1]["vector"] = [1.0] * 11
    (tmp_path / "c" / "meta_data.json").write_text(json.dumps(meta))
    with pytest.raises(m.data.dataset.DatasetError, match=r"proj_test\[1\]: vector must be 12"):
        m.load_case(tmp_path / "c")


def test_scene_xml_states_a_per_view_scan(tmp_path):
    from mi_grg.data.scene import Scan, load_scan, write_scan_xml
    case, _ = _wobbling_case()
    path = write_scan_xml(Scan(geometry=case.geometry, test_angles=case.test_angles), tmp_path / "s.xml")
    back = load_scan(path)
    np.testing.assert_array_equal(back.geometry.view_vectors(), case.geometry.view_vectors())
    np.testing.assert_array_equal(back.geometry.view_vectors(case.test_angles),
                                  case.geometry.view_vectors(case.test_angles))


def test_a_gr_run_on_a_per_view_scan_renders_in_its_own_frames(tmp_path):
    """reconstruct then ``render --run --data``: the cross-check's sensors are the data
    set's test views in their own frames, and volpath agrees with the exported field."""
    import json
    import mi_grg as m
    from mi_grg.cli import main
    from mi_grg.data.scene import load_scan
    case, allv = _wobbling_case(views=8, tests=3)
    m.save_case(case, tmp_path / "data")
    out = tmp_path / "gr"
    opts = [f"--option={o}" for o in ("iterations=20", "n_points=300", "progress=false",
                                      "holdout_every=4")]
    assert main(["reconstruct", str(tmp_path / "data"), "--method", "gr", *opts,
                 "--out", str(out)]) == 0
    assert json.loads((out / "metrics.json").read_text())["geometry"]["per_view"] is True
    assert main(["render", "--run", str(out), "--data", str(tmp_path / "data"), "--spp", "64",
                 "--det", "8", "--views", "3", "--out", str(tmp_path / "check")]) == 0
    res = json.loads((tmp_path / "check" / "crosscheck.json").read_text())
    assert res["pass"] and res["test_view_indices"] == [0, 1, 2], res["views"]
    scale = json.loads((out / "metrics.json").read_text())["geometry"]["scene_scale"]
    got = load_scan(tmp_path / "check" / "scene.xml").geometry.view_vectors()
    want = allv.view_vectors(case.test_angles) * scale
    want[:, 6:] *= 24 / 8
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------- FDK
@pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")
@pytest.mark.parametrize("shift", [0.3, -0.3])
def test_half_fan_fdk_matches_rtk(shift):
    """RTK's DisplacedDetectorImageFilter (Wang's weights, zero padding) then its FDK."""
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=circular_angles(60),
                   offDetector=(0.0, shift * 4.2))
    _same_as_rtk_fdk(geo, "DisplacedDetectorImageFilter")


def _same_as_rtk_fdk(geo, weighting):
    """Our FDK of Shepp-Logan's exact projections equals RTK's (``weighting`` first) to
    1e-4 relative."""
    from test_voxel_projector import rtk_fdk, rtk_or_skip
    from mi_grg.core.fdk import fdk
    from mi_grg.data.phantoms import make_phantom
    itk, rtk = rtk_or_skip()
    proj = make_phantom("shepp").line_integrals(geo).astype(np.float32)
    ref = rtk_fdk(itk, rtk, proj, geo, weighting)
    ours = fdk(proj, geo)
    assert np.linalg.norm(ref) > 1.0
    assert np.linalg.norm(ours - ref) <= 1e-4 * np.linalg.norm(ref)


@pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")
@pytest.mark.parametrize("start_deg, span_deg, views", [(20.0, 240.0, 80), (300.0, 215.0, 61)])
def test_short_scan_fdk_matches_rtk(start_deg, span_deg, views):
    """RTK's ParkerShortScanImageFilter then its FDK, on a short scan (one that wraps
    through 0 too)."""
    angles = np.radians(start_deg + np.linspace(0.0, span_deg, views))
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=angles)
    _same_as_rtk_fdk(geo, "ParkerShortScanImageFilter")


@pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")
def test_per_view_short_scan_fdk_matches_rtk():
    """Parker's weights of a per-view short scan take each view's own gantry angle and
    distance (its angles 1.5 degrees off the nominal ones, SID and SDD +-3 %), as RTK's."""
    from mi_grg.core.view_vectors import circular_vectors
    rng = np.random.default_rng(1)
    nominal = np.radians(20.0 + np.linspace(0.0, 240.0, 61))
    a = nominal + np.radians(rng.uniform(-1.5, 1.5, nominal.size))
    dso, dsd = (x * (1 + rng.uniform(-0.03, 0.03, a.size)) for x in (5.0, 7.0))
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=nominal)
    rows = np.stack(np.broadcast_arrays(*circular_vectors(
        np.cos(a), np.sin(a), dsd, dso, geo.dDetector, geo.offDetector)), -1)
    _same_as_rtk_fdk(geo.replace(vectors=rows), "ParkerShortScanImageFilter")


@pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")
def test_per_view_half_fan_fdk_matches_rtk():
    """Wang's weights of a per-view half-fan scan take each view's own distances (SID and
    SDD +-3 %), the overlap the narrowest of the views', as RTK's."""
    from mi_grg.core.view_vectors import circular_vectors
    rng = np.random.default_rng(2)
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=circular_angles(60),
                   offDetector=(0.0, 0.3 * 4.2))
    a = geo.angles
    dso, dsd = (x * (1 + rng.uniform(-0.03, 0.03, a.size)) for x in (5.0, 7.0))
    rows = np.stack(np.broadcast_arrays(*circular_vectors(
        np.cos(a), np.sin(a), dsd, dso, geo.dDetector, geo.offDetector)), -1)
    _same_as_rtk_fdk(geo.replace(vectors=rows), "DisplacedDetectorImageFilter")


def test_short_scan_caveats(capsys):
    """A short scan of pi plus the fan angle is FDK's; less than that, or with an offset
    detector, is named on stderr."""
    from mi_grg.core.fdk import fdk
    from mi_grg.core.fdk_geometry import caveats
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(8, 12), sDetector=(3.5, 4.2),
                   nVoxel=(8, 8, 8), sVoxel=(2.0, 1.9, 1.8),
                   angles=np.radians(np.linspace(0.0, 215.0, 40)))
    assert caveats(geo) == []                       # fan angle 2 atan(2.1 / 7) = 33.4 deg
    short = geo.with_angles(np.radians(np.linspace(0.0, 200.0, 40)))
    assert ["spans 200 degrees, less than 180 plus the fan angle (213)" in c
            for c in caveats(short)] == [True]
    fdk(np.zeros(short.projection_shape, np.float32), short)
    assert "fdk: not meaningful" in capsys.readouterr().err
    half = geo.replace(offDetector=(0.0, 1.2))
    assert ["with an offset detector" in c for c in caveats(half)] == [True]
    assert caveats(geo.with_angles(circular_angles(40))) == []


def _fdk_case(geo):
    from mi_grg.data.phantoms import make_phantom
    ph = make_phantom("shepp")
    return ph.line_integrals(geo).astype(np.float32), ph.voxelize(geo)


def test_fdk_uses_each_views_frame():
    from mi_grg.core.fdk import fdk
    from mi_grg.evaluation.metrics import psnr_3d
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(40, 48), sDetector=(3.5, 4.2),
                   nVoxel=(32, 30, 28), sVoxel=(2.0, 1.9, 1.8), angles=circular_angles(60))
    proj, gt = _fdk_case(geo)
    circ = fdk(proj, geo)
    vec = fdk(proj, geo.as_vectors())          # the per-view path on a circle
    assert np.linalg.norm(vec - circ) <= 1e-5 * np.linalg.norm(circ)
    w = wobbling(geo)
    wproj, _ = _fdk_case(w)
    own, ignored = psnr_3d(fdk(wproj, w), gt), psnr_3d(fdk(wproj, w.circular()), gt)
    assert own > psnr_3d(circ, gt) - 1.0 and own > ignored + 1.0
    # a detector whose rows are sheared against its columns (10 degrees): each pixel
    # back-projected at its own place (the dual steps), the cosine weights by distance
    sk = wobbling(geo, height=0.0, roll_deg=0.0, dsd=0.0, skew_deg=10.0)
    sproj, _ = _fdk_case(sk)
    own, ignored = psnr_3d(fdk(sproj, sk), gt), psnr_3d(fdk(sproj, sk.circular()), gt)
    assert own > psnr_3d(circ, gt) - 0.3 and own > ignored + 2.0


def test_fdk_says_where_it_is_not_meaningful(capsys):
    from mi_grg.core.fdk import fdk
    geo = scan(views=8)
    big = wobbling(geo, height=1.0, roll_deg=10.0)
    fdk(np.zeros(big.projection_shape, np.float32), big)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fdk: not meaningful" in err and "rolled" in err
    fdk(np.zeros(geo.projection_shape, np.float32), wobbling(geo))
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------- path-traced cross-check
def test_path_tracer_on_a_per_view_scan(tmp_path):
    """Mitsuba's volpath through the ct_scanner's per-view frames against the phantom's
    closed-form line integrals on the same rays; the circle's rays would fail."""
    import dataclasses
    from pathlib import Path
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.data.scene import load_scan, write_scan_xml
    from mi_grg.evaluation.crosscheck import render_scene, view_statistics
    scenes = Path(__file__).resolve().parents[1] / "scenes"
    scan = load_scan(scenes / "shepp_cone_volpath.xml")
    geo = wobbling(scan.geometry, height=0.3, roll_deg=5.0, dsd=0.05)
    path = write_scan_xml(dataclasses.replace(scan, geometry=geo), tmp_path / "wobble.xml")
    res = render_scene(path, 64, tmp_path / "out", seed=5)
    assert res["pass"], res["views"]
    assert all(0.7 < v["z_rms"] < 1.3 and v["pixels_informative"] > 100 for v in res["views"])
    mc = np.asarray(mi.Bitmap(str(tmp_path / "out" / "volpath_T.exr")), np.float64)
    mc = mc.reshape(geo.n_views, *geo.nDetector)
    circle = np.exp(-make_phantom("shepp").line_integrals(geo.circular()))
    assert not any(v["pass"] for v in view_statistics(mc, circle, 64))
