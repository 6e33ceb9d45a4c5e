"""Analytic phantoms: closed-form chords vs hand formulas, root finding, quadrature through
the voxelised ground truth, mass conservation, voxelisation vs brute-force sampling."""
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

import mi_grg  # noqa: F401  (sets up the environment before anything else)
from mi_grg.core.geometry import Geometry
from mi_grg.data.phantoms import PHANTOMS, EllipsoidPhantom, make_phantom


def sphere(centre, radius, density=1.0):
    return EllipsoidPhantom(centres=[centre], semi_axes=[[radius] * 3], rotations=[np.eye(3)],
                            densities=[density], name="sphere")


def unit_geometry(mode="parallel", **kw):
    """Volume box [-1, 1]^3 (scale 1, normalised == world coordinates)."""
    args = dict(mode=mode, DSD=7.0, DSO=5.0, nDetector=(16, 16), sDetector=(3.0, 3.0),
                nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0), angles=[0.0])
    args.update(kw)
    return Geometry(**args)


def pixel_offsets(geo):
    """Hand-written pixel positions along e_v and e_u (pixel centres, offsets included)."""
    (nv, nu), (dv, du) = geo.nDetector, geo.dDetector
    sv = (np.arange(nv) + 0.5 - nv / 2) * dv + geo.offDetector[0]
    su = (np.arange(nu) + 0.5 - nu / 2) * du + geo.offDetector[1]
    return np.meshgrid(sv, su, indexing="ij")


# ------------------------------------------------------------------ closed-form chords
@pytest.mark.parametrize("mode", ["parallel", "cone"])
def test_sphere_chords_match_hand_formula(mode):
    # Non-cubic box with an offset: the phantom maps with scale min(sVoxel)/2 = 0.8.
    geo = Geometry(mode=mode, DSD=6.0, DSO=4.0, nDetector=(21, 25), sDetector=(2.6, 3.1),
                   nVoxel=(8, 8, 8), sVoxel=(2.4, 2.0, 1.6), offOrigin=(0.1, -0.2, 0.05),
                   offDetector=(0.07, -0.11), angles=[0.0, 0.7, 2.5, 4.0])
    c_n, r_n, rho = np.array([0.3, -0.2, 0.1]), 0.5, 0.7
    ph = sphere(c_n, r_n, rho)
    C = np.array(geo.offOrigin) + 0.8 * c_n
    R = 0.8 * r_n
    got = ph.line_integrals(geo)
    sv, su = pixel_offsets(geo)
    for k, a in enumerate(geo.angles):
        n = np.array([math.cos(a), math.sin(a), 0.0])
        eu = np.array([-math.sin(a), math.cos(a), 0.0])
        ev = np.array([0.0, 0.0, -1.0])
        if mode == "parallel":
            # distance of the centre from the line through su e_u + sv e_v along n
            d2 = (C @ eu - su) ** 2 + (C @ ev - sv) ** 2
        else:
            src = geo.DSO * n
            pix = -(geo.DSD - geo.DSO) * n + su[..., None] * eu + sv[..., None] * ev
            dirs = pix - src
            dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
            d2 = (np.cross(C - src, dirs) ** 2).sum(-1)
        want = rho * 2 * np.sqrt(np.maximum(R ** 2 - d2, 0.0))
        np.testing.assert_allclose(got[k], want, rtol=1e-9, atol=1e-12)
        assert (want > 0).sum() > 20   # the sphere is really hit


@pytest.mark.parametrize("mode", ["parallel", "cone"])
def test_ray_through_centre_is_twice_the_semi_axis(mode):
    a = np.array([0.5, 0.3, 0.2])
    ph = EllipsoidPhantom(centres=[[0, 0, 0]], semi_axes=[a], rotations=[np.eye(3)],
                          densities=[0.6])
    # odd detector: the middle pixel's ray passes through the origin
    geo = unit_geometry(mode, nDetector=(31, 31), angles=[0.0, np.pi / 2])
    p = ph.line_integrals(geo)
    assert p[0, 15, 15] == pytest.approx(0.6 * 2 * a[0], rel=1e-12)   # along -x
    assert p[1, 15, 15] == pytest.approx(0.6 * 2 * a[1], rel=1e-12)   # along -y


def test_rotated_ellipsoid_matches_rays_transformed_by_hand():
    rng = np.random.default_rng(5)
    rot = Rotation.random(random_state=7).as_matrix()
    c_n, a_n = np.array([0.1, -0.15, 0.2]), np.array([0.45, 0.2, 0.3])
    ph = EllipsoidPhantom(centres=[c_n], semi_axes=[a_n], rotations=[rot], densities=[1.3])
    geo = unit_geometry(sVoxel=(3.0, 2.5, 2.8), offOrigin=(0.2, 0.1, -0.3))   # scale 1.25
    s, off = 1.25, np.array(geo.offOrigin)
    c, a = off + s * c_n, s * a_n
    # rays aimed near the centre (some miss), a few starting inside the ellipsoid
    o = c + rng.normal(size=(60, 3)) * 0.1 + 3.0 * rng.normal(size=(60, 3))
    o[:5] = c + 0.05 * rng.normal(size=(5, 3))
    d = (c + rng.normal(size=(60, 3)) * 0.5) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = ph.ray_integrals(o, d, geo)
    want = np.zeros(60)
    for i in range(60):
        ol, dl = rot.T @ (o[i] - c), rot.T @ d[i]   # ray in the ellipsoid frame
        coef = [np.sum(dl ** 2 / a ** 2), 2 * np.sum(ol * dl / a ** 2), np.sum(ol ** 2 / a ** 2) - 1]
        roots = np.roots(coef)
        if np.all(np.isreal(roots)):    # half-line: keep the part at t >= 0
            t0, t1 = np.sort(np.maximum(roots.real, 0.0))
            want[i] = 1.3 * (t1 - t0)
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    assert 10 < (want > 0).sum() < 60


def test_grazing_missing_and_inside_rays():
    r = 0.4
    ph = sphere([0, 0, 0], r, 2.0)
    geo = unit_geometry()
    offs = np.array([r * (1 + 1e-12), r * (1 + 1e-9), 2 * r, r, 0.0])
    o = np.stack([np.full(5, -3.0), offs, np.zeros(5)], 1)
    d = np.tile([1.0, 0.0, 0.0], (5, 1))
    p = ph.ray_integrals(o, d, geo)
    assert np.all(p[:3] == 0.0)                       # grazing past / missing: exactly 0
    assert np.isfinite(p[3]) and 0.0 <= p[3] < 1e-5   # exact tangent: ~0
    assert p[4] == pytest.approx(2.0 * 2 * r, rel=1e-12)
    # pointing away from the sphere: nothing ahead
    assert ph.ray_integrals([[-3.0, 0, 0]], [[-1.0, 0, 0]], geo)[0] == 0.0
    # starting at the centre: half-line r, segment 0.1 r, segment beyond the exit r
    inside = ph.ray_integrals(np.zeros((3, 3)), np.tile([0, 1.0, 0], (3, 1)), geo,
                              lengths=[np.inf, 0.1 * r, 5.0])
    np.testing.assert_allclose(inside, 2.0 * np.array([r, 0.1 * r, r]), rtol=1e-12)
    # a segment ending before the sphere
    assert ph.ray_integrals([[-3.0, 0, 0]], [[1.0, 0, 0]], geo, lengths=[2.0])[0] == 0.0


def test_parallel_start_point_inside_the_object():
    # Parallel beam: the start point sits at distance DSO from the axis; with DSO 0.5 it is
    # inside a sphere of radius 0.8, and the detector (DSD 1) is inside it as well.
    R = 0.8
    geo = unit_geometry(DSD=1.0, DSO=0.5, nDetector=(9, 9), sDetector=(2.0, 2.0),
                        angles=[0.3, 2.0])
    p = sphere([0, 0, 0], R).line_integrals(geo)
    sv, su = pixel_offsets(geo)
    h = np.sqrt(np.maximum(R ** 2 - su ** 2 - sv ** 2, 0))
    want = np.where(h > 0, np.minimum(1.0, 0.5 + h) - np.maximum(0.0, 0.5 - h), 0.0)
    for k in range(2):
        np.testing.assert_allclose(p[k], want, rtol=1e-12, atol=1e-14)
    assert np.any(want == 1.0) and np.any((want > 0) & (want < 1.0))


def test_line_integrals_finite_and_zero_off_the_object():
    geo = unit_geometry("cone", nDetector=(40, 40), sDetector=(8.0, 8.0), angles=[0.2, 1.9])
    for name in PHANTOMS:
        p = make_phantom(name).line_integrals(geo)
        assert np.all(np.isfinite(p)) and p.min() >= 0.0
        assert np.all(p[:, :5, :] == 0.0) and np.all(p[:, :, -5:] == 0.0)   # rays miss
        assert p.max() > 0.1


@pytest.mark.parametrize("name", PHANTOMS)
def test_parallel_projection_conserves_mass(name):
    # Parallel beam: the integral of each projection over the detector is the total mass.
    ph = make_phantom(name)
    geo = unit_geometry(nDetector=(160, 160), sDetector=(3.0, 3.0), angles=[0.4, 2.2])
    p = ph.line_integrals(geo)
    mass = np.sum(ph.densities * 4 / 3 * np.pi * np.prod(ph.semi_axes, 1))
    dv, du = geo.dDetector
    np.testing.assert_allclose(p.sum((1, 2)) * dv * du, mass, rtol=2e-3)


# ------------------------------------------------------------------ vs voxelised quadrature
def march(vol, geo, step):
    """Independent line integrals: march every pixel ray (float64, midpoint rule) through
    the trilinearly interpolated volume [x, y, z]."""
    ax = geo.voxel_axes()
    o, d = geo.pixel_rays_numpy()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_mid = np.einsum("ij,ij->i", -o, d)                 # closest approach to the centre
    ts = np.arange(-math.sqrt(3), math.sqrt(3), step) + step / 2
    pts = o[:, None] + (t_mid[:, None] + ts[None])[..., None] * d[:, None]   # [ray, s, 3]
    idx = [(pts[..., j] - ax[j][0]) / (ax[j][1] - ax[j][0]) for j in range(3)]
    vals = map_coordinates(vol.astype(np.float64), [i.reshape(-1) for i in idx], order=1,
                           mode="constant", cval=0.0)
    return vals.reshape(pts.shape[:2]).sum(1).reshape(geo.projection_shape) * step


@pytest.fixture(scope="module")
def voxelised():
    """Every family voxelised at 32^3, 64^3 and 128^3 on the [-1, 1]^3 box."""
    geo = unit_geometry()
    return {(name, n): make_phantom(name).voxelize(geo.replace(nVoxel=(n, n, n)))
            for name in PHANTOMS for n in (32, 64, 128)}


@pytest.mark.parametrize("mode,sdet", [("cone", 3.4), ("parallel", 2.4)])
@pytest.mark.parametrize("name", PHANTOMS)
def test_closed_form_matches_quadrature_through_voxels(voxelised, name, mode, sdet):
    ph = make_phantom(name)
    geo = unit_geometry(mode, nDetector=(12, 12), sDetector=(sdet, sdet),
                        angles=[0.3, 1.4, 2.9])
    exact = ph.line_integrals(geo)
    errs = []
    for n in (32, 64, 128):
        g = geo.replace(nVoxel=(n, n, n))
        errs.append(np.abs(march(voxelised[name, n], g, 0.5 / n) - exact).mean())
    scale = np.abs(exact).mean()
    assert errs[0] > 1.5 * errs[1] and errs[1] > 1.5 * errs[2], errs   # falls with refinement
    assert errs[2] < 0.035 * scale, (errs, scale)


# ------------------------------------------------------------------ voxelisation
def brute_voxelize(ph, geo, s):
    """Mean of ``density`` over all s^3 sub-voxel points of every voxel."""
    ax = geo.voxel_axes()
    frac = (np.arange(s) + 0.5) / s - 0.5
    sub = [(a[:, None] + frac[None] * d).reshape(-1) for a, d in zip(ax, geo.dVoxel)]
    pts = np.stack(np.meshgrid(*sub, indexing="ij"), -1)
    dens = ph.density(pts, geo)
    nx, ny, nz = geo.nVoxel
    return dens.reshape(nx, s, ny, s, nz, s).mean((1, 3, 5))


@pytest.mark.parametrize("name", PHANTOMS)
def test_voxelize_equals_brute_force_sampling(name):
    geo = unit_geometry(nVoxel=(13, 11, 9), sVoxel=(2.2, 2.0, 2.6), offOrigin=(0.1, 0.0, -0.2))
    ph = make_phantom(name, seed=3)
    for s in (1, 3):
        got = ph.voxelize(geo, supersample=s)
        assert got.dtype == np.float32 and got.shape == (13, 11, 9)
        np.testing.assert_allclose(got, brute_voxelize(ph, geo, s), atol=1e-6)


def test_off_centre_sphere_lands_at_the_right_index():
    geo = unit_geometry(nVoxel=(20, 16, 12), sVoxel=(2.5, 2.0, 1.5), offOrigin=(0.3, -0.1, 0.2))
    s, off = 0.75, np.array(geo.offOrigin)        # scale = min(sVoxel) / 2
    c_n, r_n = np.array([0.6, -0.4, 0.2]), 0.2
    vol = sphere(c_n, r_n, 0.9).voxelize(geo)
    world = off + s * c_n
    lo = off - np.array(geo.sVoxel) / 2
    want = np.floor((world - lo) / np.array(geo.dVoxel)).astype(int)
    assert np.unravel_index(np.argmax(vol), vol.shape) == tuple(want)   # x is axis 0
    ax = np.meshgrid(*geo.voxel_axes(), indexing="ij")
    com = np.array([(vol * a).sum() for a in ax]) / vol.sum()
    np.testing.assert_allclose(com, world, atol=0.05 * min(geo.dVoxel))
    mass = vol.sum() * np.prod(geo.dVoxel)
    assert mass == pytest.approx(0.9 * 4 / 3 * np.pi * (s * r_n) ** 3, rel=0.02)


def surface_points(ph, per=2000, seed=0):
    """Points just inside and just outside every ellipsoid's surface (normalised)."""
    rng = np.random.default_rng(seed)
    out = []
    for c, a, r in zip(ph.centres, ph.semi_axes, ph.rotations):
        u = rng.normal(size=(per, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        surf = (u * a) @ r.T
        out += [c + surf * (1 - 1e-6), c + surf * (1 + 1e-6)]
    return np.concatenate(out)


@pytest.mark.parametrize("name", PHANTOMS)
def test_densities_within_unit_interval(name):
    geo = unit_geometry(nVoxel=(48, 48, 48))     # world == normalised
    for seed in (0, 1):
        ph = make_phantom(name, seed=seed)
        pts = np.concatenate([np.random.default_rng(seed).uniform(-1, 1, (200_000, 3)),
                              surface_points(ph, seed=seed)])
        dens = ph.density(pts, geo)
        assert dens.min() >= 0.0 and dens.max() <= 1.0, (dens.min(), dens.max())
        vol = ph.voxelize(geo, supersample=2)
        assert vol.min() >= 0.0 and vol.max() <= 1.0 and vol.max() > 0.5


def test_shepp_region_values():
    geo = unit_geometry()
    d = make_phantom("shepp").density(
        [[0.0, 0.0, 0.0],          # brain
         [0.0, 0.9, 0.0],          # skull (between the outer two ellipsoids)
         [0.22, 0.0, 0.0],         # ventricle
         [0.0, 0.35, -0.15],       # large central feature
         [0.0, 0.0, 0.95]], geo)   # air
    np.testing.assert_allclose(d, [0.2, 1.0, 0.0, 0.3, 0.0], atol=1e-12)


# ------------------------------------------------------------------ families and validation
def test_make_phantom_names_and_seeds():
    assert PHANTOMS == ("shepp", "needles", "shells", "blobs")
    with pytest.raises(ValueError, match="shepp, needles, shells, blobs"):
        make_phantom("walnut")
    for name in ("needles", "shells", "blobs"):
        a, b, c = make_phantom(name, 1), make_phantom(name, 1), make_phantom(name, 2)
        assert np.array_equal(a.centres, b.centres) and np.array_equal(a.densities, b.densities)
        assert not np.array_equal(a.centres, c.centres)
        assert a.name == name


def test_needle_family_shape():
    ph = make_phantom("needles", seed=4)
    needles = ph.semi_axes[1:]
    assert len(needles) == 10
    assert np.all((needles[:, 0] >= 0.02) & (needles[:, 0] <= 0.04))   # 1-2 % of edge 2
    assert np.all(needles[:, 2] >= 5 * needles[:, 0])                   # elongated
    dirs = ph.rotations[1:, :, 2]
    assert np.abs(dirs @ dirs.T - np.eye(10)).max() > 0.1               # not all parallel
    assert ph.densities[0] == pytest.approx(0.1)


def test_shells_have_negative_inner_ellipsoids_and_inclusions():
    ph = make_phantom("shells")
    assert np.sum(ph.densities < 0) == 3 and len(ph) == 14
    assert np.all(ph.semi_axes[6:].max(1) <= 0.07)


def test_blobs_overlap_at_most_three_deep():
    # The family's bound on density rests on each blob's bounding sphere meeting at most two
    # earlier ones (then no point lies in more than three blobs); the rule must bind.
    most, deepest = 0, 0.0
    for seed in range(12):
        ph = make_phantom("blobs", seed=seed)
        assert len(ph) == 15 and ph.densities[0] == pytest.approx(0.1)
        assert np.all((ph.densities[1:] >= 0.1) & (ph.densities[1:] <= 0.3))
        c, r = ph.centres[1:], ph.semi_axes[1:].max(1)
        meets = np.linalg.norm(c[:, None] - c[None], axis=-1) < r[:, None] + r[None]
        earlier = np.tril(meets, -1).sum(1)
        assert earlier.max() <= 2
        most = max(most, earlier.max())
        blobs = EllipsoidPhantom(centres=c, semi_axes=ph.semi_axes[1:],
                                 rotations=ph.rotations[1:], densities=np.ones(14))
        pts = np.concatenate([np.random.default_rng(seed).uniform(-1, 1, (100_000, 3)), c])
        depth = blobs.density(pts, unit_geometry(nVoxel=(48, 48, 48)))
        assert depth.max() <= 3.0
        deepest = max(deepest, depth.max())
    assert most == 2 and deepest >= 2.0


def test_phantom_validation():
    ok = dict(centres=[[0, 0, 0]], semi_axes=[[0.5, 0.5, 0.5]], rotations=[np.eye(3)],
              densities=[1.0])
    EllipsoidPhantom(**ok)
    bad = [dict(semi_axes=[[0.5, 0.0, 0.5]]), dict(centres=[[0.8, 0, 0]]),
           dict(rotations=[2 * np.eye(3)]), dict(rotations=[-np.eye(3)]),
           dict(densities=[np.nan]), dict(centres=[[0, 0]]), dict(densities=[1.0, 2.0])]
    for change in bad:
        with pytest.raises(ValueError):
            EllipsoidPhantom(**{**ok, **change})
    ph = EllipsoidPhantom(**ok)
    with pytest.raises(ValueError, match="points"):
        ph.density(np.zeros((4, 2)), unit_geometry())
    with pytest.raises(ValueError, match="supersample"):
        ph.voxelize(unit_geometry(), supersample=0)
    with pytest.raises(ValueError, match="non-zero"):
        ph.ray_integrals([[0, 0, 0]], [[0, 0, 0]], unit_geometry())
