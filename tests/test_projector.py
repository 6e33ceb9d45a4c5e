"""Radiative-Gaussian projector (mi_grg.core.projector, plugins/rg_projector.py).

References are independent of the implementation: float64 NumPy line integrals on the
rays of ``Geometry.pixel_rays_numpy`` (closed form written with Sigma^-1 = R S^-2 R^T and
its own quaternion formula; the half-line form cross-checked by quadrature), central
finite differences of that reference, dot-product (adjoint) identities and the chain rule.
"""
import math

import numpy as np
import pytest
from scipy.special import ndtr

import mi_grg
from mi_grg.core.geometry import circular_angles

E_BIG = 9.0   # truncation error exp(-81/2) ~ 3e-18: compares the closed form itself


# ---------------------------------------------------------------- references (float64)
def quat_matrix(q):
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def reference(geo, pos, scales, rots, rho, half=False, angles=None):
    """Untruncated line integrals [view, v, u]; ``half``: cone-beam rays start at the source."""
    o, d = geo.pixel_rays_numpy(angles)
    R = quat_matrix(rots)
    A = np.einsum("nij,nj,nkj->nik", R, 1.0 / np.asarray(scales, np.float64) ** 2, R)
    out = np.zeros(o.shape[:-1])
    for i in range(len(rho)):
        w = o - pos[i]
        a = np.einsum("...i,ij,...j->...", d, A[i], d)
        b = np.einsum("...i,ij,...j->...", d, A[i], w)
        c = np.einsum("...i,ij,...j->...", w, A[i], w)
        f = ndtr(-b / np.sqrt(a)) if half else 1.0
        out += rho[i] * np.sqrt(2 * np.pi / a) * np.exp(-0.5 * (c - b * b / a)) * f
    return out


def as_arrays(g):
    n = g.numpy()
    return [n[k].astype(np.float64) for k in ("positions", "scales", "rotations", "densities")]


def random_gaussians(rng, n, spread=0.6, smin=0.05, smax=0.3):
    from mi_grg.core.gaussians import Gaussians
    q = rng.normal(size=(n, 4))
    return Gaussians.from_numpy(rng.uniform(-spread, spread, (n, 3)),
                                rng.uniform(smin, smax, (n, 3)),
                                q / np.linalg.norm(q, axis=1, keepdims=True),
                                rng.uniform(0.5, 2.0, n))


def geometry(mode="cone", nd=(24, 32), views=3, offsets=True, **kw):
    extra = dict(offOrigin=(0.1, -0.05, 0.08), offDetector=(0.12, -0.2)) if offsets else {}
    extra.update(kw)
    return mi_grg.Geometry(mode=mode, DSD=7.0, DSO=5.0, nDetector=nd, sDetector=(3.0, 4.0),
                           nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0),
                           angles=circular_angles(views) + 0.3, **extra)


def grads_numpy(dr, arrays):
    out = []
    for a in arrays:
        g = dr.grad(a)
        out.append(np.asarray(g, np.float64) if isinstance(g, type(a)) and len(g.shape) == 1
                   else np.stack([np.asarray(c, np.float64) for c in g], -1))
    return out


def scalar(x):
    return float(np.asarray(x, np.float64).ravel()[0])


def truncation_bound(arrays, extent):
    """Sum over Gaussians of (largest possible line integral) * exp(-E^2/2)."""
    _, s, _, rho = arrays
    return math.exp(-0.5 * extent ** 2) * float(np.sum(rho * np.sqrt(2 * np.pi) * s.max(1)))


# ---------------------------------------------------------------- accuracy
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_matches_float64_bruteforce(variant, mode, rng):
    from mi_grg.core.projector import DEFAULT_EXTENT, project
    geo = geometry(mode)
    g = random_gaussians(rng, 25)
    arr = as_arrays(g)
    ref = reference(geo, *arr)
    peak = ref.max()
    img = project(g, geo)
    assert img.shape == (3, 24, 32) and img.dtype == np.float32
    err = np.abs(img - ref)
    assert err.max() <= 1e-4 * peak                          # default extent: truncation
    assert err.max() <= truncation_bound(arr, DEFAULT_EXTENT) + 2e-6 * peak
    big = ref > 0.1 * peak
    assert np.all(err[big] <= 2e-4 * ref[big])
    # no truncation: the closed form on every true ray, to float32 precision
    exact = project(g, geo, extent=E_BIG)
    assert np.abs(exact - ref).max() <= 3e-6 * peak
    sig = ref > 0.01 * peak
    assert np.all(np.abs(exact - ref)[sig] <= 2e-5 * ref[sig])


def test_extent_tradeoff_is_monotone(rng):
    from mi_grg.core.projector import project
    geo = geometry("cone", views=2)
    g = random_gaussians(rng, 15)
    arr = as_arrays(g)
    ref = reference(geo, *arr)
    errs = [np.abs(project(g, geo, extent=e) - ref).max() for e in (2.0, 3.0, 4.0, 5.0)]
    for e, err in zip((2.0, 3.0, 4.0, 5.0), errs):
        assert err <= truncation_bound(arr, e) + 3e-6 * ref.max()
    assert errs[0] > errs[1] > errs[2]
    assert errs[0] > 1e-3 * ref.max()          # truncating at 2 sigma is visibly wrong


# ---------------------------------------------------------------- linearity / adjoint
def test_linear_in_densities_and_adjoint(variant, rng):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.projector import project, project_dr
    geo = geometry("cone", views=2)
    g = random_gaussians(rng, 12)
    n = len(g)
    r1, r2 = rng.uniform(0, 2, n), rng.uniform(0, 2, n)
    p1 = project(g.replace(densities=mi.Float(r1)), geo).astype(np.float64)
    p2 = project(g.replace(densities=mi.Float(r2)), geo).astype(np.float64)
    p12 = project(g.replace(densities=mi.Float(0.7 * r1 + 1.3 * r2)), geo).astype(np.float64)
    assert np.abs(p12 - (0.7 * p1 + 1.3 * p2)).max() <= 2e-6 * np.abs(p12).max()
    # <P rho, y> = <rho, P^T y>, P^T y being the density gradient of <P rho, y>
    y = rng.normal(size=p1.shape)
    rho = mi.Float(r1)
    dr.enable_grad(rho)
    img = project_dr(g.replace(densities=rho), geo)
    dr.backward(dr.sum(img.array * mi.Float(y.ravel().astype(np.float32))))
    pty = np.asarray(dr.grad(rho), np.float64)
    lhs = float(np.sum(p1 * y))
    rhs = float(np.sum(r1.astype(np.float32) * pty))
    assert abs(lhs - rhs) <= 1e-5 * np.sum(np.abs(p1 * y))
    # each entry of P^T y is <P e_i, y> (column-wise adjoint)
    for i in (0, 5, 11):
        e = np.zeros(n)
        e[i] = 1.0
        col = project(g.replace(densities=mi.Float(e)), geo).astype(np.float64)
        assert abs(np.sum(col * y) - pty[i]) <= 1e-5 * np.sum(np.abs(col * y)) + 1e-7


# ---------------------------------------------------------------- gradients
def _fd(fun, params, key, h=1e-6):
    out = np.zeros_like(params[key])
    for idx in np.ndindex(params[key].shape):
        pp = {k: v.copy() for k, v in params.items()}
        pm = {k: v.copy() for k, v in params.items()}
        pp[key][idx] += h
        pm[key][idx] -= h
        out[idx] = (fun(pp) - fun(pm)) / (2 * h)
    return out


@pytest.mark.parametrize("case", ["cone", "parallel", "near_source", "skewed cone",
                                  "skewed parallel", "skewed near_source"])
def test_gradients_all_parameters_vs_finite_differences(variant, case, rng):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project_dr
    from mi_grg.data.orbits import wobbling
    skewed = case.startswith("skewed ")
    case = case.removeprefix("skewed ")
    geo = geometry("parallel" if case == "parallel" else "cone", nd=(12, 16), views=2)
    if skewed:      # the pixel rows sheared by ~6 degrees against the columns, source kept
        geo = wobbling(geo, height=0.0, roll_deg=0.0, dsd=0.0, skew_deg=12.0)
    if case == "near_source":   # one Gaussian straddling the source, one regular, one close
        src = 5.0 * np.array([math.cos(geo.angles[0]), math.sin(geo.angles[0]), 0.0])
        pos = np.stack([src * 0.93 + [0, 0.05, 0.02], [0.2, -0.1, 0.1], src * 0.7])
        sc = np.array([[0.5, 0.2, 0.3], [0.2, 0.3, 0.25], [0.4, 0.3, 0.2]])
    else:
        pos = rng.uniform(-0.5, 0.5, (3, 3))
        sc = rng.uniform(0.1, 0.3, (3, 3))
    q = rng.normal(size=(3, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians.from_numpy(pos, sc, q, rng.uniform(0.5, 2.0, 3))
    ds = mi.Float(rng.uniform(0.5, 1.5, 3))
    y = rng.normal(size=(2, 12, 16))
    leaves = [g.positions, g.scales, g.rotations, g.densities, ds]
    for a in leaves:
        dr.enable_grad(a)
    img = project_dr(g, geo, extent=E_BIG, density_scale=ds)
    dr.backward(dr.sum(img.array * mi.Float(y.ravel().astype(np.float32))))
    got = dict(zip(("positions", "scales", "rotations", "densities", "ds"), grads_numpy(dr, leaves)))
    p0 = dict(zip(("positions", "scales", "rotations", "densities"), as_arrays(g)))
    p0["ds"] = np.asarray(ds, np.float64)
    half = case == "near_source"

    def loss(p):
        return np.sum(reference(geo, p["positions"], p["scales"], p["rotations"],
                                p["densities"] * p["ds"], half=half) * y)

    for key in got:
        fd = _fd(loss, p0, key)
        assert np.all(np.isfinite(got[key]))
        assert np.abs(fd).max() > 1e-3, key
        np.testing.assert_allclose(got[key], fd, rtol=0, atol=2e-4 * np.abs(fd).max() + 1e-6,
                                   err_msg=key)


def test_forward_mode_matches_backward(variant, rng):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.projector import project_dr
    geo = geometry("cone", nd=(12, 16), views=2)
    src = 5.0 * np.array([math.cos(geo.angles[1]), math.sin(geo.angles[1]), 0.0])
    g = random_gaussians(rng, 4, spread=0.4)
    pos = np.stack([np.asarray(c) for c in g.positions], -1)
    pos[0] = 0.95 * src                                   # one near-source record too
    g = g.replace(positions=mi.Point3f(*[mi.Float(pos[:, k]) for k in range(3)]))
    y = mi.Float(rng.normal(size=2 * 12 * 16).astype(np.float32))
    leaves = [g.positions, g.scales, g.rotations, g.densities]
    tangents = [type(a)(*[mi.Float(rng.normal(size=4).astype(np.float32)) for _ in range(len(a))])
                if len(a.shape) == 2 else mi.Float(rng.normal(size=4).astype(np.float32))
                for a in leaves]
    for a, t in zip(leaves, tangents):
        dr.enable_grad(a)
        dr.set_grad(a, t)
    img = project_dr(g, geo)
    dr.forward_to(img.array)
    fwd = scalar(dr.sum(dr.grad(img.array) * y))
    for a in leaves:
        dr.set_grad(a, 0)
    img = project_dr(g, geo)
    dr.backward(dr.sum(img.array * y))
    bwd = sum(scalar(dr.sum(dr.grad(a) * t, axis=None)) for a, t in zip(leaves, tangents))
    assert abs(fwd - bwd) <= 1e-4 * max(abs(fwd), 1.0)
    assert abs(fwd) > 1e-2


def plane_gradients(geo, y):
    """One Gaussian's ``means2d`` gradient [view, 2] of <project_dr(geo), y> and, from each
    view projected alone, its 3-D position gradient [view, 3]; with the Gaussian."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project_dr
    pos, sc = np.array([[0.15, -0.1, 0.2]]), np.array([[0.2, 0.12, 0.3]])
    q = np.array([[0.9, 0.2, -0.3, 0.1]])
    q /= np.linalg.norm(q)
    g = Gaussians.from_numpy(pos, sc, q, [1.5])
    md = dr.zeros(mi.Vector2f, geo.n_views)
    dr.enable_grad(md)
    img = project_dr(g, geo, means2d=md)
    dr.backward(dr.sum(img.array * mi.Float(y.ravel().astype(np.float32))))
    gmd = np.stack([np.asarray(c, np.float64) for c in dr.grad(md)], -1)
    gp = []
    for k in range(geo.n_views):
        gk = Gaussians.from_numpy(pos, sc, q, [1.5])
        dr.enable_grad(gk.positions)
        im = project_dr(gk, geo, angles=geo.angles[k:k + 1])
        dr.backward(dr.sum(im.array * mi.Float(y[k].ravel().astype(np.float32))))
        gp.append([float(c[0]) for c in dr.grad(gk.positions)])
    return gmd, np.array(gp), g


def test_detector_plane_gradient(variant, rng):
    """means2d gradient == 3-D position gradient of that view along (e_u, e_v) times the
    pixel size at the Gaussian's depth; and == FD of moving the Gaussian in that plane."""
    geo = geometry("cone", nd=(16, 20), views=2, offsets=False)
    y = rng.normal(size=(2, 16, 20))
    gmd, gp, g = plane_gradients(geo, y)
    pos = as_arrays(g)[0]
    fr = geo.detector_frame()
    du, dv = geo.dDetector[1], geo.dDetector[0]
    for k in range(2):
        depth = np.dot(pos[0] - fr["source"][k], -fr["normal"][k])
        scale = depth / geo.DSD
        want = [gp[k] @ fr["e_u"][k] * du * scale, gp[k] @ fr["e_v"][k] * dv * scale]
        np.testing.assert_allclose(gmd[k], want, rtol=1e-4, atol=1e-6)
        # FD with the float64 reference: move the centre by h pixels in the plane
        arr = as_arrays(g)
        for axis, e, d in ((0, fr["e_u"][k], du), (1, fr["e_v"][k], dv)):
            h = 1e-4
            vals = []
            for sgn in (1, -1):
                p = arr[0] + sgn * h * d * scale * e
                vals.append(np.sum(reference(geo, p, *arr[1:], angles=geo.angles[k:k + 1]) * y[k]))
            fd = (vals[0] - vals[1]) / (2 * h)
            assert abs(fd - gmd[k, axis]) <= 2e-4 * max(abs(fd), 1e-2), (k, axis, fd, gmd[k])
    assert np.abs(gmd).min() > 1e-3


# ---------------------------------------------------------------- hard cases
def _needles(rng, n, s):
    from mi_grg.core.gaussians import Gaussians
    q = rng.normal(size=(n, 4))
    return Gaussians.from_numpy(rng.uniform(-0.6, 0.6, (n, 3)), np.tile(s, (n, 1)),
                                q / np.linalg.norm(q, axis=1, keepdims=True), np.full(n, 1e3))


@pytest.mark.parametrize("shape", ["needle", "pancake", "mixed"])
def test_needles_and_near_singular_covariances(shape, rng):
    from mi_grg.core.projector import DEFAULT_EXTENT, project
    geo = geometry("cone", nd=(48, 64), views=3)
    s = {"needle": (0.3, 3e-5, 3e-5), "pancake": (0.3, 0.3, 3e-5), "mixed": (0.2, 2e-5, 0.05)}[shape]
    g = _needles(rng, 30, s)
    arr = as_arrays(g)
    ref = reference(geo, *arr)
    exact = project(g, geo, extent=E_BIG)
    assert np.all(np.isfinite(exact)) and ref.max() > 0
    # Rays grazing a 2e-5-thin needle/sheet edge-on: the value changes by O(1) within
    # 1e-3 pixel while float32 ray positions carry ~3e-7 absolute error (|o| = 5).
    tol = 1e-4 if shape == "pancake" else 5e-3
    assert np.abs(exact - ref).max() <= tol * ref.max()
    img = project(g, geo)
    assert np.all(np.isfinite(img))
    assert np.abs(img - ref).max() <= truncation_bound(arr, DEFAULT_EXTENT) + tol * ref.max()


def test_large_line_integrals_and_far_from_origin(rng):
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project
    geo = geometry("cone", views=2)
    g = random_gaussians(rng, 20, smin=0.05, smax=0.2)
    dense = g.replace(densities=g.densities * 500.0)
    ref = reference(geo, *as_arrays(dense))
    assert ref.max() > 100
    img = project(dense, geo, extent=E_BIG)
    assert np.abs(img - ref).max() <= 3e-6 * ref.max()
    # the same scene 100x larger: |p| ~ 100, DSO = 500; line integrals scale by 100
    # (scale invariance only: sizes grow with |p|, so no cancellation; see the next test)
    arr = as_arrays(g)
    big = Gaussians.from_numpy(arr[0] * 100, arr[1] * 100, arr[2], arr[3])
    geo100 = geo.scaled(100.0)
    ref100 = reference(geo100, *as_arrays(big))
    img100 = project(big, geo100, extent=E_BIG)
    ref1 = 100 * reference(geo, *arr)     # float32 rounding of the x100 inputs: ~1e-7
    assert np.abs(ref100 - ref1).max() <= 1e-5 * ref1.max()
    assert np.abs(img100 - ref100).max() <= 3e-6 * ref100.max()


def test_small_gaussians_far_from_origin(rng):
    """float32 cancellation: Gaussians of sigma 0.05-0.3 about 1000 units from the origin
    along the beam (DSO = 1500, 500 units from the source), against the float64 reference
    at the default extent. Evaluating c - b^2/a of the closed form in float32 there is off
    by orders of magnitude; the projector's frame-relative form measured 3.9e-5 of the peak
    (2-7e-5 over view angles: half an ulp of a 1000-unit coordinate, 3e-5, is 6e-4 sigma)."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project
    a0 = 0.3
    centre = 1000.0 * np.array([np.cos(a0), np.sin(a0), 0.0])   # on the central ray
    geo = mi_grg.Geometry(mode="cone", DSD=2000.0, DSO=1500.0, nDetector=(48, 48),
                          sDetector=(12.0, 12.0), nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0),
                          offOrigin=tuple(centre), angles=[a0])
    n = 20
    q = rng.normal(size=(n, 4))
    g = Gaussians.from_numpy(centre + rng.uniform(-0.6, 0.6, (n, 3)),
                             rng.uniform(0.05, 0.3, (n, 3)),
                             q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(0.5, 2.0, n))
    arr = as_arrays(g)      # the float32-rounded inputs: only the arithmetic is compared
    assert np.linalg.norm(arr[0], axis=1).min() > 998
    ref = reference(geo, *arr)
    peak = ref.max()
    assert peak > 1.0 and np.mean(ref > 0.01 * peak) > 0.1   # the cluster is in view
    img = project(g, geo)
    assert np.all(np.isfinite(img))
    assert np.abs(img - ref).max() <= 1e-4 * peak


def test_source_straddling_behind_and_at_source(variant):
    import drjit as dr
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project, project_dr
    geo = geometry("cone", views=3, offsets=False)
    a0 = geo.angles[0]
    n0 = np.array([math.cos(a0), math.sin(a0), 0.0])
    cases = {"at source": (5.0 * n0, (0.3, 0.2, 0.25)),
             "behind": (5.4 * n0 + [0, 0, 0.05], (0.3, 0.2, 0.25)),
             "far behind": (9.0 * n0, (0.3, 0.2, 0.25)),
             "straddling": (4.6 * n0 + [0.05, 0.1, 0], (0.5, 0.2, 0.3)),
             "contains source": ((0.0, 0.0, 0.0), (3.0, 2.0, 2.5)),
             "close in front": (3.0 * n0 + [0, 0.3, 0.1], (0.3, 0.2, 0.25))}
    q = np.array([[0.8, 0.3, -0.4, 0.33]])
    q /= np.linalg.norm(q)
    for name, (p, s) in cases.items():
        g = Gaussians.from_numpy([p], [s], q, [1.0])
        arr = as_arrays(g)
        ref = reference(geo, *arr, half=True)
        img = project(g, geo, extent=E_BIG)
        assert np.all(np.isfinite(img)), name
        assert np.abs(img - ref).max() <= 5e-6 * max(ref.max(), 1e-3), name
        whole = reference(geo, *arr, half=False)
        if name in ("behind", "straddling", "far behind"):
            assert np.abs(whole - ref).max() > 1e-2 * whole.max(), name   # the case matters
        # gradients exist and are finite
        for a in (g.positions, g.scales, g.rotations, g.densities):
            dr.enable_grad(a)
        im = project_dr(g, geo)
        dr.backward(dr.sum(im.array))
        for a in (g.positions, g.scales, g.rotations, g.densities):
            assert bool(dr.all(dr.isfinite(dr.grad(a)), axis=None)), name
    # the half-line closed form itself, by quadrature along one ray of the straddling case
    g = Gaussians.from_numpy([cases["straddling"][0]], [cases["straddling"][1]], q, [1.0])
    arr = as_arrays(g)
    o, d = geo.pixel_rays_numpy()
    o, d = o[0, 12, 16], d[0, 12, 16]
    A = quat_matrix(arr[2])[0] @ np.diag(1 / arr[1][0] ** 2) @ quat_matrix(arr[2])[0].T
    t = np.linspace(0.0, 12.0, 240001)
    x = o + t[:, None] * d - arr[0][0]
    f = np.exp(-0.5 * np.einsum("ti,ij,tj->t", x, A, x))
    quad = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(t)))
    assert abs(reference(geo, *arr, half=True)[0, 12, 16] - quad) <= 1e-7 * max(quad, 1)
    assert abs(project(g, geo, extent=E_BIG)[0, 12, 16] - quad) <= 1e-5 * max(quad, 1)


def test_grazing_rays_and_partial_footprints(rng):
    """End-on needles along rays, Gaussians hanging over the detector edge, footprints
    larger than the detector."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project
    geo = geometry("cone", nd=(20, 24), views=2, offsets=False)
    fr = geo.detector_frame()
    src, nrm = fr["source"][0], -fr["normal"][0]
    corner = fr["center"][0] + 1.45 * fr["e_u"][0] + 1.0 * fr["e_v"][0]
    d = (corner - src) / np.linalg.norm(corner - src)
    # a needle lying along the ray through a point near the detector corner
    R = np.linalg.qr(np.column_stack([d, rng.normal(size=(3, 2))]))[0]
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
    w = math.sqrt(max(1 + R[0, 0] + R[1, 1] + R[2, 2], 1e-12)) / 2
    qn = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    pos = np.stack([src + 5.0 * d, src + 5.2 * nrm + 1.1 * fr["e_u"][0], [0.0, 0.0, 0.0]])
    sc = np.array([[0.4, 2e-3, 2e-3], [0.3, 0.3, 0.3], [2.0, 0.05, 1.5]])
    g = Gaussians.from_numpy(pos, sc, np.stack([qn, [1, 0, 0, 0], [1, 0, 0, 0]]), [1.0, 1.0, 1.0])
    arr = as_arrays(g)
    ref = reference(geo, *arr)
    img = project(g, geo, extent=E_BIG)
    assert np.all(np.isfinite(img))
    assert np.abs(img - ref).max() <= 1e-5 * ref.max()


def test_zero_gaussians_and_chunking(variant, rng, monkeypatch):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core import projector as P
    from mi_grg.core.gaussians import Gaussians
    geo = geometry("cone", nd=(12, 16), views=3)
    empty = Gaussians(positions=mi.Point3f(), scales=mi.Vector3f(), rotations=mi.Vector4f(),
                      densities=mi.Float())
    z = P.project(empty, geo)
    assert z.shape == (3, 12, 16) and not z.any()
    # chunked records / row batches give the same images and gradients
    g = random_gaussians(rng, 7)
    src = 5.0 * np.array([math.cos(geo.angles[2]), math.sin(geo.angles[2]), 0.0])
    pos = np.stack([np.asarray(c) for c in g.positions], -1)
    pos[3] = 0.9 * src
    g = g.replace(positions=mi.Point3f(*[mi.Float(pos[:, k]) for k in range(3)]))
    y = mi.Float(rng.normal(size=3 * 12 * 16).astype(np.float32))

    def run():
        gg = Gaussians(*[type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)])
        for a in (gg.positions, gg.scales, gg.densities):
            dr.enable_grad(a)
        img = P.project_dr(gg, geo)
        dr.backward(dr.sum(img.array * y))
        return np.asarray(img.array), [grads_numpy(dr, [a])[0]
                                       for a in (gg.positions, gg.scales, gg.densities)]

    img0, g0 = run()
    monkeypatch.setattr(P, "RECORDS_PER_CHUNK", 5)
    monkeypatch.setattr(P, "ROWS_PER_BATCH", 37)
    monkeypatch.setattr(P, "PIXELS_PER_CHUNK", 2 * 12 * 16)     # 2 views per chunk
    img1, g1 = run()
    monkeypatch.setattr(P, "RECORDS_PER_CHUNK", 1 << 20)          # views split by pixels only
    img2, g2 = run()
    for im, gr in ((img1, g1), (img2, g2)):
        np.testing.assert_allclose(im, img0, rtol=1e-5, atol=1e-6 * img0.max())
        for a, b in zip(g0, gr):
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * np.abs(a).max())


def test_packet_path_equals_per_pixel_path(rng, monkeypatch):
    """The LLVM kernels' packets (PACKET-pixel stores into rows padded to a whole number
    of packets, one packet load per lane, the backward's per-record packet sums) give the
    per-pixel path's image, gradients and tangents: on a detector width that is not a
    multiple of PACKET, with a near-source Gaussian, several views and row batches."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core import lanes, projector as P
    from mi_grg.core.gaussians import Gaussians
    if not lanes.use_packets():
        pytest.skip("packets are the LLVM backend's path")
    geo = geometry("cone", nd=(12, 13), views=3)
    assert geo.nDetector[1] % P.PACKET
    g = random_gaussians(rng, 9)
    src = 5.0 * np.array([math.cos(geo.angles[1]), math.sin(geo.angles[1]), 0.0])
    pos = np.stack([np.asarray(c) for c in g.positions], -1)
    pos[4] = 0.9 * src                                   # straddles the source: near record
    g = g.replace(positions=mi.Point3f(*[mi.Float(pos[:, k]) for k in range(3)]))
    y = mi.Float(rng.normal(size=3 * 12 * 13).astype(np.float32))
    t_pos = rng.normal(size=(3, 9)).astype(np.float32)

    def run():
        gg = Gaussians(*[type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)])
        leaves = (gg.positions, gg.scales, gg.rotations, gg.densities)
        for a in leaves:
            dr.enable_grad(a)
        img = P.project_dr(gg, geo)
        dr.backward(dr.sum(img.array * y))
        grads = [grads_numpy(dr, [a])[0] for a in leaves]
        # forward mode: tangent along random position directions
        gt = Gaussians(*[type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)])
        dr.enable_grad(gt.positions)
        img_t = P.project_dr(gt, geo)
        dr.set_grad(gt.positions, mi.Point3f(*[mi.Float(t) for t in t_pos]))
        tangent = np.asarray(dr.forward_to(img_t.array))
        return np.asarray(img.array), grads, tangent

    img_pk, g_pk, t_pk = run()
    monkeypatch.setattr(P, "ROWS_PER_BATCH", 23)             # several batches per record sum
    img_b, g_b, t_b = run()
    monkeypatch.setattr(P, "ROWS_PER_BATCH", 1 << 22)
    monkeypatch.setattr(lanes, "EXPAND_BYTES", 0)            # per-parameter scatter-adds
    img_s, g_s, t_s = run()
    monkeypatch.setattr(lanes, "use_packets", lambda: False)  # the per-pixel path (CUDA's)
    img_px, g_px, t_px = run()
    assert img_px.shape == (3 * 12 * 13,) and img_px.max() > 0
    for im, gr, tan in ((img_pk, g_pk, t_pk), (img_b, g_b, t_b), (img_s, g_s, t_s)):
        np.testing.assert_allclose(im, img_px, rtol=1e-5, atol=1e-6 * img_px.max())
        np.testing.assert_allclose(tan, t_px, rtol=1e-4, atol=1e-5 * np.abs(t_px).max())
        for a, b in zip(g_px, gr):
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * np.abs(a).max())


def test_invalid_inputs_are_rejected(variant):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians, GaussiansError
    from mi_grg.core.projector import ProjectorError, project, project_dr
    geo = geometry("cone", nd=(8, 8), views=1)
    good = Gaussians.from_numpy([[0.0, 0.0, 0.0], [0.1, 0.2, 0.0]], [[0.1, 0.1, 0.1]] * 2)
    with pytest.raises(GaussiansError, match="scales"):
        Gaussians.from_numpy([[0.0, 0, 0]], [[-0.1, 0.1, 0.1]])

    def bad(**kw):
        return good.replace(**kw)

    nan_pos = mi.Point3f(mi.Float(0.0, float("nan")), mi.Float(0.0, 0.0), mi.Float(0.0, 0.0))
    with pytest.raises(ProjectorError, match="positions"):
        project(bad(positions=nan_pos), geo)
    with pytest.raises(ProjectorError, match="scales"):
        project(bad(scales=mi.Vector3f(mi.Float(0.1, -0.1), 0.1, 0.1)), geo)
    with pytest.raises(ProjectorError, match="densities"):
        project(bad(densities=mi.Float(1.0, float("inf"))), geo)
    with pytest.raises(ProjectorError, match="rotations"):
        project(bad(rotations=mi.Vector4f(mi.Float(1.0, 0.0), 0.0, 0.0, 0.0)), geo)   # zero q
    with pytest.raises(ProjectorError, match="rotations"):
        project(bad(rotations=mi.Vector4f(mi.Float(1.0, 1.1), 0.0, 0.0, 0.0)), geo)   # |q| = 1.1
    with pytest.raises(ProjectorError, match="density_scale"):
        project(good, geo, density_scale=mi.Float(1.0, 2.0, 3.0))
    with pytest.raises(ProjectorError, match="means2d"):
        project_dr(good, geo, means2d=dr.zeros(mi.Vector2f, 3))
    with pytest.raises(ProjectorError, match="extent"):
        project(good, geo, extent=0.0)
    with pytest.raises(ProjectorError, match="geometry"):
        project(good, {"mode": "cone"})


def test_million_gaussians(rng):
    """10^6 Gaussians: finite, additive over subsets (chunking), exact on sampled pixels.
    Not marked slow (~4-9 s on the 2-core CPU), so the default test run covers it."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project
    n = 1_000_000
    geo = geometry("cone", nd=(64, 64), views=2)
    x = rng.normal(size=(n, 3))
    x *= (rng.uniform(0, 1, (n, 1)) ** (1 / 3)) / np.linalg.norm(x, axis=1, keepdims=True)
    s = 0.5 * (4.19 / n) ** (1 / 3) * np.exp(rng.normal(0, 0.3, (n, 3)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rho = rng.uniform(0.1, 1.0, n)
    g = Gaussians.from_numpy(x, s, q, rho)
    img = project(g, geo)
    assert np.all(np.isfinite(img)) and img.max() > 0
    half = n // 2
    parts = [Gaussians.from_numpy(x[sl], s[sl], q[sl], rho[sl]) for sl in (slice(0, half), slice(half, n))]
    summed = project(parts[0], geo).astype(np.float64) + project(parts[1], geo)
    assert np.abs(summed - img).max() <= 1e-5 * img.max()
    arr = as_arrays(g)
    o, d = geo.pixel_rays_numpy()
    R = quat_matrix(arr[2])
    A = np.einsum("nij,nj,nkj->nik", R, 1.0 / arr[1] ** 2, R)
    flat = np.argsort(img.ravel())
    picks = [flat[-1], flat[int(0.8 * flat.size)], flat[int(0.6 * flat.size)]]
    for (k, i, j) in (np.unravel_index(f, img.shape) for f in picks):
        assert img[k, i, j] > 1e-3 * img.max()
        w = o[k, i, j] - arr[0]
        a = np.einsum("i,nij,j->n", d[k, i, j], A, d[k, i, j])
        b = np.einsum("i,nij,nj->n", d[k, i, j], A, w)
        c = np.einsum("ni,nij,nj->n", w, A, w)
        ref = np.sum(arr[3] * np.sqrt(2 * np.pi / a) * np.exp(-0.5 * (c - b * b / a)))
        assert abs(img[k, i, j] - ref) <= 2e-4 * ref


# ---------------------------------------------------------------- Mitsuba integrator
def _scene(mi, geo, filename=None, extent=None):
    nv, nu = geo.nDetector
    sensor = {"type": "ct_scanner", "mode": geo.mode, "DSD": geo.DSD, "DSO": geo.DSO,
              "nDetector": f"{nv} {nu}", "sDetector": " ".join(map(str, geo.sDetector)),
              "nVoxel": " ".join(map(str, geo.nVoxel)), "sVoxel": " ".join(map(str, geo.sVoxel)),
              "offOrigin": " ".join(map(str, geo.offOrigin)),
              "offDetector": " ".join(map(str, geo.offDetector)),
              "angles": " ".join(repr(float(a)) for a in geo.angles)}
    integ = {"type": "rg_projector"}
    if filename:
        integ["filename"] = str(filename)
    if extent:
        integ["extent"] = extent
    return mi.load_dict({"type": "scene", "integrator": integ, "sensor": sensor})


def test_integrator_renders_and_differentiates(variant, rng, tmp_path):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.projector import project, project_dr
    geo = geometry("cone", nd=(12, 16), views=2)
    g = random_gaussians(rng, 6)
    g.save_npz(tmp_path / "g.npz")
    scene = _scene(mi, geo, tmp_path / "g.npz", extent=5.0)
    params = mi.traverse(scene)
    for k in ("positions", "scales", "rotations", "densities"):
        assert f"integrator.{k}" in params
    img = mi.render(scene)
    assert tuple(img.shape) == (2 * 12, 16, 1)
    want = project(g, geo, extent=5.0)
    np.testing.assert_allclose(scene.sensors()[0].to_projections(img), want, rtol=0,
                               atol=1e-6 * want.max())
    # gradients through mi.render(params=...) == gradients of project_dr
    y = rng.normal(size=(24, 16, 1)).astype(np.float32)
    for k in ("positions", "densities"):
        dr.enable_grad(params[f"integrator.{k}"])
    params.update()
    img = mi.render(scene, params=params)
    dr.backward(dr.sum(img * mi.TensorXf(y), axis=None))
    g2 = random_gaussians(np.random.default_rng(1234), 6)   # same draw as g
    for a in (g2.positions, g2.densities):
        dr.enable_grad(a)
    im = project_dr(g2, geo, extent=5.0)
    dr.backward(dr.sum(im.array * mi.Float(y.ravel())))
    for k, a in (("positions", g2.positions), ("densities", g2.densities)):
        got = grads_numpy(dr, [params[f"integrator.{k}"]])[0]
        want = grads_numpy(dr, [a])[0]
        assert np.abs(want).max() > 1e-3
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())
    # forward mode through mi.render: <J t, y> equals <t, J^T y> from the backward pass
    gpos = grads_numpy(dr, [params["integrator.positions"]])[0]
    t = rng.normal(size=(6, 3)).astype(np.float32)
    dr.set_grad(params["integrator.positions"], mi.Point3f(*[mi.Float(t[:, k]) for k in range(3)]))
    dr.set_grad(params["integrator.densities"], 0)
    img = mi.render(scene, params=params)
    dr.forward_to(img)
    fwd = float(np.sum(np.asarray(dr.grad(img), np.float64) * y))
    assert abs(fwd - float(np.sum(gpos * t))) <= 1e-4 * np.sum(np.abs(gpos * t))
    # an optimiser step through the scene parameters lowers a loss
    opt = mi.ad.Adam(lr=0.02)
    opt["integrator.densities"] = params["integrator.densities"]
    params.update(opt)
    target = mi.TensorXf(np.zeros((24, 16, 1), np.float32))
    losses = []
    for _ in range(3):
        img = mi.render(scene, params=params)
        loss = dr.sum(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        params.update(opt)
        losses.append(scalar(loss.array))
    assert losses[2] < losses[0]


def test_integrator_empty_and_inconsistent_parameters(variant):
    import mitsuba as mi
    from mi_grg.core.projector import ProjectorError
    geo = geometry("parallel", nd=(6, 8), views=2)
    scene = _scene(mi, geo)
    img = mi.render(scene)
    assert tuple(img.shape) == (12, 8, 1) and not np.asarray(img).any()
    params = mi.traverse(scene)
    params["integrator.densities"] = mi.Float(1.0, 2.0)
    with pytest.raises(ProjectorError, match="densities"):
        params.update()
