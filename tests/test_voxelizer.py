"""Voxelizer vs float64 NumPy brute force, finite differences, adjoint and line integrals."""
import numpy as np
import pytest

import mi_grg
import drjit as dr
import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry
from mi_grg.core import voxelizer
from mi_grg.core.voxelizer import VoxelizerError, voxelize, voxelize_dr, DEFAULT_EXTENT


# ---------------------------------------------------------------- float64 references
def quat_to_matrix(q):
    """Rotation matrices [N, 3, 3] of quaternions (w, x, y, z), the textbook formula."""
    w, x, y, z = np.asarray(q, np.float64).T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def inverse_covariances(scales, q):
    """inv(R S S^T R^T) by np.linalg.inv (independent of mi_grg's closed form)."""
    R = quat_to_matrix(q)
    cov = R @ (np.asarray(scales, np.float64)[:, :, None] ** 2 * np.transpose(R, (0, 2, 1)))
    return np.linalg.inv(cov)


def brute_volume(params, geometry, extent, block=None):
    """sum_i rho_i exp(-m^2/2) [m <= extent] at every voxel centre, float64, all pairs."""
    pos, scales, q, rho = (np.asarray(params[k], np.float64) for k in ("pos", "scales", "q", "rho"))
    axes = geometry.voxel_axes()
    if block is not None:
        (s0, s1, s2), (n0, n1, n2) = block
        axes = (axes[0][s0:s0 + n0], axes[1][s1:s1 + n1], axes[2][s2:s2 + n2])
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    A = inverse_covariances(scales, q)
    out = np.zeros(X.shape[:3])
    for i in range(len(rho)):
        d = X - pos[i]
        m2 = np.einsum("...i,ij,...j->...", d, A[i], d)
        out += np.where(m2 <= extent ** 2, rho[i] * np.exp(-0.5 * m2), 0.0)
    return out


def closed_form_line_integrals(params, geometry):
    """Untruncated line integrals through every pixel centre [view, v, u], float64:
    int rho exp(-(a t^2 + 2 b t + c)/2) dt = rho sqrt(2 pi / a) exp(-(c - b^2/a)/2)."""
    o, d = geometry.pixel_rays_numpy()
    A = inverse_covariances(params["scales"], params["q"])
    out = np.zeros(o.shape[:3])
    for i, (p, rho) in enumerate(zip(params["pos"], params["rho"])):
        r = o - p
        a = np.einsum("...i,ij,...j->...", d, A[i], d)
        b = np.einsum("...i,ij,...j->...", d, A[i], r)
        c = np.einsum("...i,ij,...j->...", r, A[i], r)
        out += rho * np.sqrt(2 * np.pi / a) * np.exp(-0.5 * (c - b * b / a))
    return out


def make_params(rng, n, geometry, spread=0.5, smin=0.08, smax=0.3):
    centre = np.asarray(geometry.offOrigin)
    half = np.asarray(geometry.sVoxel) / 2
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {"pos": centre + rng.uniform(-spread, spread, (n, 3)) * half,
            "scales": rng.uniform(smin, smax, (n, 3)), "q": q,
            "rho": rng.uniform(0.3, 2.0, n)}


def to_gaussians(params, exact_rotations=False):
    """Gaussians from float64 params; exact_rotations skips from_numpy's normalisation so
    that perturbed (non-unit) quaternions reach the voxelizer as given."""
    g = Gaussians.from_numpy(params["pos"], params["scales"], None, params["rho"])
    q = np.asarray(params["q"], np.float64)
    return g.replace(rotations=mi.Vector4f(*[mi.Float(q[:, k]) for k in range(4)]))


@pytest.fixture
def geo():
    """Non-cubic grid, anisotropic voxels, volume centre off the origin."""
    return Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(16, 16), sDetector=(4.0, 4.0),
                    nVoxel=(20, 26, 14), sVoxel=(2.0, 2.4, 1.6), offOrigin=(0.15, -0.2, 0.1),
                    angles=[0.3, 1.9])


# ---------------------------------------------------------------- values
def test_default_extent_is_shared_with_the_projector():
    from mi_grg.core.projector import DEFAULT_EXTENT as projector_extent
    assert DEFAULT_EXTENT == projector_extent


def test_matches_brute_force(variant, geo, rng):
    params = make_params(rng, 9, geo)
    ref = brute_volume(params, geo, DEFAULT_EXTENT)
    vol = voxelize(to_gaussians(params), geo)
    assert vol.shape == geo.nVoxel and vol.dtype == np.float32
    assert np.abs(vol - ref).max() <= 1e-5 * ref.max()
    # the truncation matters at this tolerance: an untruncated sum differs
    full = brute_volume(params, geo, 1e3)
    assert np.abs(full - ref).max() > 1e-5 * ref.max()


def test_tiny_and_huge_gaussians(geo, rng):
    """Gaussians narrower than a voxel (boxes of 0 or 1 voxel) and wider than the grid."""
    params = make_params(rng, 6, geo, smin=0.005, smax=0.02)
    params["scales"][:2] = rng.uniform(1.0, 3.0, (2, 3))
    ref = brute_volume(params, geo, DEFAULT_EXTENT)
    vol = voxelize(to_gaussians(params), geo)
    assert np.abs(vol - ref).max() <= 1e-5 * ref.max()


def test_block_is_the_slice_of_the_full_volume(geo, rng):
    params = make_params(rng, 8, geo)
    g = to_gaussians(params)
    full = voxelize(g, geo)
    block = ((3, 5, 2), (9, 12, 7))
    sub = voxelize(g, geo, block=block)
    assert sub.shape == (9, 12, 7)
    np.testing.assert_allclose(sub, full[3:12, 5:17, 2:9], rtol=1e-6, atol=1e-6 * full.max())
    np.testing.assert_allclose(sub, brute_volume(params, geo, DEFAULT_EXTENT, block),
                               rtol=0, atol=1e-5 * full.max())


def test_chunking_gives_the_same_volume(geo, rng):
    g = to_gaussians(make_params(rng, 8, geo))
    ref = voxelize(g, geo)
    for chunk in (1, 97, 5000):
        np.testing.assert_allclose(voxelize(g, geo, chunk_pairs=chunk), ref,
                                   rtol=1e-6, atol=1e-6 * ref.max())
    # the chunks really were cut (one plan with several chunks, also inside a box), for the
    # forward's column lanes and the backward's slice lanes
    plan = voxelizer._plan(g.positions, g.scales, g.rotations, geo, (0, 0, 0), geo.nVoxel,
                           DEFAULT_EXTENT, 97)
    assert len(plan.col_chunks) > 8 and len(plan.slice_chunks) > 8


def test_packet_columns_match_brute_force(rng, monkeypatch):
    """Blocks whose z size is a whole number of packets take the packet path on LLVM
    (PACKET voxels per store, a block starting anywhere); it equals the float64 brute force
    and the per-voxel path, and the backward's packed Gaussian values give the gradients of
    the gathers."""
    from mi_grg.core import lanes, projector
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(16, 16), sDetector=(4.0, 4.0),
                   nVoxel=(12, 10, 2 * projector.PACKET), sVoxel=(2.0, 1.8, 2.2),
                   offOrigin=(0.1, 0.05, -0.1), angles=[0.3])
    params = make_params(rng, 10, geo)
    g = to_gaussians(params)
    blocks = [None, ((2, 1, 3), (8, 7, projector.PACKET))]
    y = [rng.normal(size=geo.nVoxel if b is None else b[1]) for b in blocks]
    if lanes.use_packets():
        plan = voxelizer._plan(g.positions, g.scales, g.rotations, geo, (0, 0, 0), geo.nVoxel,
                               DEFAULT_EXTENT, voxelizer.DEFAULT_CHUNK_PAIRS)
        assert voxelizer._use_packets(plan)

    def run():
        vols, grads = [], []
        for b, yb in zip(blocks, y):
            vols.append(voxelize(g, geo, block=b))
            gg = to_gaussians(params)
            dr.enable_grad(gg.positions, gg.scales, gg.densities)
            v = voxelize_dr(gg, geo, block=b)
            dr.backward(dr.sum(v.array * mi.Float(yb.ravel().astype(np.float32))))
            grads.append([np.stack([np.asarray(c) for c in dr.grad(gg.positions)], -1),
                          np.stack([np.asarray(c) for c in dr.grad(gg.scales)], -1),
                          np.asarray(dr.grad(gg.densities))])
        return vols, grads

    vols, grads = run()
    for b, vol in zip(blocks, vols):
        ref = brute_volume(params, geo, DEFAULT_EXTENT, b)
        assert ref.max() > 0
        assert np.abs(vol - ref).max() <= 1e-5 * ref.max()
    monkeypatch.setattr(voxelizer, "_use_packets", lambda plan: False)
    monkeypatch.setattr(voxelizer, "_pack_chunk", lambda *a: None)
    vols0, grads0 = run()
    for vol, vol0, gr, gr0 in zip(vols, vols0, grads, grads0):
        np.testing.assert_allclose(vol, vol0, rtol=1e-6, atol=1e-6 * vol0.max())
        for a, b in zip(gr, gr0):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * np.abs(b).max())


class _Caps:
    """The column and slice lanes of a capacity plan (as step.PairCapacity)."""

    def __init__(self, cols, slices):
        self.cols, self.slices = cols, slices
        self.cols_total = self.slices_total = None


@pytest.mark.parametrize("z", [8, 7])           # packet columns (LLVM) and per-voxel ones
def test_capacity_block_equals_the_traced_plan(rng, z):
    """A recorded step's TV block (``voxelize_block_capacity``: one chunk of capacity
    lanes over every Gaussian, the lanes past the counts skipped by a conditional) gives
    the traced plan's volume and gradients, with no spare lane, a few (the last SIMD
    packet mixed) and far more lanes than the counts; it returns the counts."""
    threads = dr.thread_count()
    dr.set_thread_count(1)        # float atomics in one order: both paths bit for bit
    try:
        geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(16, 16),
                       sDetector=(4.0, 4.0), nVoxel=(14, 12, 16), sVoxel=(2.0, 1.8, 2.2),
                       offOrigin=(0.1, 0.05, -0.1), angles=[0.3])
        params = make_params(rng, 40, geo)
        ds = mi.Float(rng.uniform(0.5, 2.0, 40).astype(np.float32))
        start, size = (3, 2, 5), (9, 8, z)
        y = mi.Float(rng.normal(size=int(np.prod(size))).astype(np.float32))

        def run(caps=None):
            g = to_gaussians(params)
            dr.enable_grad(g.positions, g.scales, g.rotations, g.densities)
            if caps is None:
                vol = voxelize_dr(g, geo, block=(start, size), density_scale=ds)
            else:
                vol = voxelizer.voxelize_block_capacity(
                    g, geo, [mi.Int32(s) for s in start], size, DEFAULT_EXTENT, ds, caps)
            dr.backward(dr.sum(vol.array * y))
            grads = [np.asarray(dr.grad(c)) for v in (g.positions, g.scales, g.rotations)
                     for c in v] + [np.asarray(dr.grad(g.densities))]
            return np.asarray(vol.array), grads

        vol, grads = run()
        counts = _Caps(1, 1)
        run(counts)
        cols, slices = int(counts.cols_total[0]), int(counts.slices_total[0])
        g = to_gaussians(params)
        plan = voxelizer._plan(g.positions, g.scales, g.rotations, geo, start, size,
                               DEFAULT_EXTENT, voxelizer.DEFAULT_CHUNK_PAIRS)
        assert cols == sum(c[2] for c in plan.col_chunks) > 0
        assert slices == sum(c[2] for c in plan.slice_chunks) > 0
        for extra in (0, 3, 5 * cols):
            caps = _Caps(cols + extra, slices + extra)
            v, gr = run(caps)
            np.testing.assert_array_equal(v, vol)
            for a, b in zip(gr, grads):
                np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7 * np.abs(b).max())
            assert int(caps.cols_total[0]) == cols and int(caps.slices_total[0]) == slices
    finally:
        dr.set_thread_count(threads)


def test_density_scale_scales_densities(geo, rng):
    params = make_params(rng, 7, geo)
    s = rng.uniform(0.2, 3.0, 7)
    a = voxelize(to_gaussians(params), geo, density_scale=mi.Float(s))
    scaled = dict(params, rho=params["rho"] * s)
    b = voxelize(to_gaussians(scaled), geo)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * b.max())


def test_zero_gaussians_give_zeros(geo):
    g = Gaussians.from_numpy(np.zeros((0, 3)), np.zeros((0, 3)))
    vol = voxelize(g, geo)
    assert vol.shape == geo.nVoxel and not vol.any()
    assert voxelize(g, geo, block=((1, 1, 1), (4, 5, 6))).shape == (4, 5, 6)


def test_gaussians_outside_the_block_give_zeros(geo, rng):
    params = make_params(rng, 3, geo, smin=0.02, smax=0.03)
    params["pos"][:] = np.asarray(geo.bbox()[1]) + 1.0
    assert not voxelize(to_gaussians(params), geo).any()


def test_rejects_bad_input(geo, rng):
    g = to_gaussians(make_params(rng, 3, geo))
    bad = np.array([[np.nan, 0, 0], [0, 0, 0], [0, 0, 0]])
    with pytest.raises(VoxelizerError, match="positions"):
        voxelize(g.replace(positions=mi.Point3f(*[mi.Float(bad[:, k]) for k in range(3)])), geo)
    with pytest.raises(VoxelizerError, match="density_scale"):
        voxelize(g, geo, density_scale=mi.Float([1.0, 2.0]))
    with pytest.raises(VoxelizerError, match="density_scale"):
        voxelize(g, geo, density_scale=mi.Float([1.0, np.inf, 1.0]))
    with pytest.raises(VoxelizerError, match="block"):
        voxelize(g, geo, block=((0, 0, 0), (100, 2, 2)))
    with pytest.raises(VoxelizerError, match="extent"):
        voxelize(g, geo, extent=-1.0)
    # the projector's checks: zero / non-unit quaternions, negative densities and scales
    from mi_grg.core.gaussians import QUATERNION_TOL
    from mi_grg.core.projector import ProjectorError, project
    q = np.asarray(g.numpy()["rotations"], np.float64)
    tol = QUATERNION_TOL

    def rot(rows):
        return mi.Vector4f(*[mi.Float(rows[:, k]) for k in range(4)])

    cases = {
        "zero quaternion": (dict(rotations=rot(np.vstack([q[:2], np.zeros((1, 4))]))),
                            "rotations contains a zero quaternion"),
        "|q| = 2": (dict(rotations=rot(q * 2.0)), "rotations must be unit"),
        "|q| = 1 - 3 tol": (dict(rotations=rot(q * np.array([[1.0], [1 - 3 * tol], [1.0]]))),
                            "rotations must be unit"),
        "NaN rotation": (dict(rotations=rot(np.vstack([q[:2], [[np.nan, 0, 0, 1]]]))),
                         "rotations .* NaN"),
        "negative density": (dict(densities=mi.Float([0.5, -1e-3, 1.0])), "densities must be >= 0"),
        "Inf density": (dict(densities=mi.Float([0.5, np.inf, 1.0])), "densities .* Inf"),
        "zero scale": (dict(scales=mi.Vector3f(mi.Float([0.1, 0.1, 0.1]), mi.Float([0.1, 0.0, 0.1]),
                                               mi.Float([0.1, 0.1, 0.1]))), "scales must be > 0"),
    }
    for name, (change, msg) in cases.items():
        bad_g = g.replace(**change)
        with pytest.raises(VoxelizerError, match=msg):
            voxelize(bad_g, geo)
        with pytest.raises(VoxelizerError, match=msg):   # the training entry point too
            voxelize_dr(bad_g, geo, block=((0, 0, 0), (4, 4, 4)))
        with pytest.raises(ProjectorError, match=msg):   # one check for both
            project(bad_g, geo)
    # the first failing check is reported (positions before densities)
    both = g.replace(positions=mi.Point3f(*[mi.Float(bad[:, k]) for k in range(3)]),
                     densities=mi.Float([0.5, -1.0, 1.0]))
    with pytest.raises(VoxelizerError, match="positions"):
        voxelize(both, geo)


def test_rotations_are_normalised_internally(geo, rng):
    """Quaternions within QUATERNION_TOL of unit length give the volume of their normalised
    selves, and the rotation gradient has no radial component (tangent to the sphere)."""
    from mi_grg.core.gaussians import QUATERNION_TOL
    params = make_params(rng, 6, geo, smin=0.12, smax=0.3)
    unit = voxelize(to_gaussians(params), geo)
    stretch = 1 + 0.8 * QUATERNION_TOL * np.array([1, -1, 1, -1, 1, -1.0])[:, None]
    off = dict(params, q=params["q"] * stretch)
    np.testing.assert_allclose(voxelize(to_gaussians(off), geo), unit, rtol=0,
                               atol=2e-6 * unit.max())
    y = rng.normal(size=geo.nVoxel)
    gq = _ad_grads(off, geo, y)["q"]
    radial = np.sum(gq * off["q"], 1) / np.linalg.norm(off["q"], axis=1)
    assert np.linalg.norm(gq) > 0
    assert np.abs(radial).max() <= 1e-5 * np.abs(gq).max()


# ---------------------------------------------------------------- derivatives
FD_EXTENT = 6.0  # truncation jump rho e^-18: invisible to finite differences


def _loss64(params, geo, y, block=None):
    return float(np.sum(brute_volume(params, geo, FD_EXTENT, block) * y))


def _ad_grads(params, geo, y, block=None, density_scale=None):
    g = to_gaussians(params)
    ds = None if density_scale is None else mi.Float(density_scale)
    dr.enable_grad(g.positions, g.scales, g.rotations, g.densities)
    if ds is not None:
        dr.enable_grad(ds)
    vol = voxelize_dr(g, geo, block=block, extent=FD_EXTENT, density_scale=ds)
    dr.backward(dr.sum(vol.array * mi.Float(y.ravel().astype(np.float32))))
    stack = lambda v: np.stack([np.asarray(c, np.float64) for c in v], -1)  # noqa: E731
    out = {"pos": stack(dr.grad(g.positions)), "scales": stack(dr.grad(g.scales)),
           "q": stack(dr.grad(g.rotations)), "rho": np.asarray(dr.grad(g.densities), np.float64)}
    if ds is not None:
        out["density_scale"] = np.asarray(dr.grad(ds), np.float64)
    return out


@pytest.mark.parametrize("block", [None, ((4, 3, 2), (10, 14, 9))])
def test_gradients_match_central_differences(variant, geo, rng, block):
    params = make_params(rng, 5, geo, smin=0.12, smax=0.3)
    shape = geo.nVoxel if block is None else block[1]
    y = rng.normal(size=shape)
    grads = _ad_grads(params, geo, y, block)
    for key in ("pos", "scales", "q", "rho"):
        delta = rng.normal(size=params[key].shape)
        if key == "q":  # stay on the unit sphere to first order
            delta -= np.sum(delta * params["q"], 1, keepdims=True) * params["q"]
        eps = 1e-5
        hi = _loss64(dict(params, **{key: params[key] + eps * delta}), geo, y, block)
        lo = _loss64(dict(params, **{key: params[key] - eps * delta}), geo, y, block)
        fd = (hi - lo) / (2 * eps)
        ad = float(np.sum(grads[key] * delta))
        assert ad == pytest.approx(fd, rel=2e-3, abs=1e-3 * np.abs(grads[key]).sum()), key


def test_density_scale_gradient(geo, rng):
    params = make_params(rng, 4, geo)
    s = rng.uniform(0.5, 2.0, 4)
    y = rng.normal(size=geo.nVoxel)
    grads = _ad_grads(params, geo, y, density_scale=s)
    # d/ds_i of sum rho_i s_i G_i(x) y(x) = rho_i <G_i, y> = rho_i / s_i * d/drho_i
    np.testing.assert_allclose(grads["density_scale"], grads["rho"] * params["rho"] / s,
                               rtol=1e-4)
    unit = {}
    for i in range(4):
        one = dict(params, rho=np.eye(4)[i] * params["rho"])
        unit[i] = _loss64(one, geo, y)
    np.testing.assert_allclose(grads["density_scale"], [unit[i] for i in range(4)], rtol=1e-3,
                               atol=1e-4 * max(abs(v) for v in unit.values()))


def test_adjoint_dot_product(variant, geo, rng):
    """<V rho, y> = <rho, V^T y> with V^T y from reverse-mode AD (V is linear in rho)."""
    params = make_params(rng, 12, geo)
    y = rng.normal(size=geo.nVoxel)
    g = to_gaussians(params)
    dr.enable_grad(g.densities)
    vol = voxelize_dr(g, geo)
    lhs = float(np.sum(vol.numpy().astype(np.float64) * y))
    dr.backward(dr.sum(vol.array * mi.Float(y.ravel().astype(np.float32))))
    rhs = float(np.sum(params["rho"] * np.asarray(dr.grad(g.densities), np.float64)))
    assert lhs == pytest.approx(rhs, rel=1e-5)


def test_forward_mode_equals_reverse_mode(geo, rng):
    params = make_params(rng, 5, geo)
    y = rng.normal(size=geo.nVoxel)
    delta = {k: rng.normal(size=params[k].shape) for k in ("pos", "scales", "rho")}
    g = to_gaussians(params)
    arrays = {"pos": g.positions, "scales": g.scales, "rho": g.densities}
    for key, arr in arrays.items():
        dr.enable_grad(arr)
        d = delta[key]
        dr.set_grad(arr, mi.Float(d) if d.ndim == 1 else type(arr)(*[mi.Float(d[:, k])
                                                                     for k in range(3)]))
    vol = voxelize_dr(g, geo, extent=FD_EXTENT)
    tangent = np.asarray(dr.forward_to(vol.array), np.float64)
    grads = _ad_grads(params, geo, y)
    rev = sum(float(np.sum(grads[k] * delta[k])) for k in delta)
    assert float(np.sum(tangent * y.ravel())) == pytest.approx(rev, rel=1e-4)


# ---------------------------------------------------------------- line integrals
def _integrate_volume(vol, geometry):
    """Line integrals of the trilinear interpolant between voxel centres (dr.dda)."""
    from mi_grg.evaluation.crosscheck import integrate_volume
    return integrate_volume(vol, geometry)


def test_voxelize_then_integrate_converges_to_closed_form(rng):
    """Closed-form projections vs dr.dda integrals of the voxelised field: the error falls
    ~4x per halving of the voxel size (trilinear interpolation is second order)."""
    base = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(12, 12), sDetector=(3.0, 3.0),
                    nVoxel=(32, 32, 32), sVoxel=(2.0, 2.0, 2.0), offOrigin=(0.1, 0.0, -0.05),
                    angles=[0.2, 1.4])
    params = make_params(rng, 4, base, spread=0.35, smin=0.1, smax=0.25)
    g = to_gaussians(params)
    ref = closed_form_line_integrals(params, base)
    from mi_grg.core.projector import project
    # the projector's closed form agrees with ours
    np.testing.assert_allclose(project(g, base, extent=FD_EXTENT), ref, rtol=1e-4,
                               atol=1e-5 * ref.max())
    errors = []
    for n in (32, 64, 128):
        geo = base.replace(nVoxel=(n, n, n))
        proj = _integrate_volume(voxelize(g, geo, extent=FD_EXTENT), geo)
        errors.append(np.abs(proj - ref).max() / ref.max())
    assert errors[0] < 0.05
    assert errors[1] < errors[0] / 2.5 and errors[2] < errors[1] / 2.5, errors
