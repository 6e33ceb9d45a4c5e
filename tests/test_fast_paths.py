"""Fast paths equal the general ones they shortcut (projector and voxelizer).

Projector (mi_grg.core.projector): a training iteration projects ONE view of ALL
Gaussians: then the records are the Gaussians themselves (no compaction to the regular
records, no index gathers) and the (record, row) lanes are expanded on the device. A
multi-view call takes the general path (records gathered per view, compacted; here also
host-expanded row batches when ROWS_PER_BATCH is small). Both must give the same image
and the same gradients of every input, including near-source records (exact half-line
form), records outside the detector, the graph field's density_scale and the
detector-plane offsets means2d.

Voxelizer (mi_grg.core.voxelizer): the forward's column index of a lane is split into
(x, y) with a float32 division where that is exact (boxes of < 2^22 columns), else with
integer division; the backward runs on (Gaussian, x) slice lanes. Both splits, and small
chunks cut inside boxes, must give the same block and gradients.
"""
import math

import numpy as np
import pytest

import mi_grg
from mi_grg.core.geometry import circular_angles


def _case(rng, n=40):
    from mi_grg.core.gaussians import Gaussians
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(20, 28), sDetector=(3.0, 4.0),
                          nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0),
                          angles=circular_angles(3) + 0.3, offOrigin=(0.1, -0.05, 0.08))
    q = rng.normal(size=(n, 4))
    pos = rng.uniform(-0.7, 0.7, (n, 3))
    src = 5.0 * np.array([math.cos(geo.angles[1]), math.sin(geo.angles[1]), 0.0])
    scales = rng.uniform(0.05, 0.3, (n, 3))
    # 0.9 in front of the source of view 1, 7.5 Mahalanobis units away (< sqrt(4.5^2 + 8^2)):
    # a near record with a well-formed footprint there
    pos[3], scales[3] = 0.82 * src, 0.12
    pos[5] = (4.0, 4.0, 3.5)       # off every detector: no rows
    g = Gaussians.from_numpy(pos, scales,
                             q / np.linalg.norm(q, axis=1, keepdims=True),
                             rng.uniform(0.5, 2.0, n))
    return geo, g, rng.uniform(0.8, 1.5, n).astype(np.float32)


def _run(geo, g, scale, angles, weights):
    """Image and gradients of sum(image * weights) w.r.t. every input."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project_dr
    leaves = [type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)]
    ds = mi.Float(scale)
    md = dr.zeros(mi.Vector2f, len(g) * len(angles))
    for a in leaves + [ds, md]:
        dr.enable_grad(a)
    img = project_dr(Gaussians(*leaves), geo, angles=angles, density_scale=ds, means2d=md)
    dr.backward(dr.sum(img.array * mi.Float(weights.ravel())))

    def arr(x):
        x = dr.grad(x)
        return (np.asarray(x, np.float64) if dr.depth_v(x) == 1
                else np.stack([np.asarray(c, np.float64) for c in x], -1))
    return np.asarray(img.numpy(), np.float64).reshape(img.shape), [arr(a) for a in leaves + [ds, md]]


@pytest.mark.parametrize("small_batches", [False, True])
def test_single_view_path_equals_general_path(variant, rng, monkeypatch, small_batches):
    from mi_grg.core import projector as P
    geo, g, scale = _case(rng)
    n = len(g)
    nv, nu = geo.nDetector
    y = rng.normal(size=(nv, nu)).astype(np.float32)
    if small_batches:   # host-expanded row batches for the single-view call too
        monkeypatch.setattr(P, "ROWS_PER_BATCH", 37)
    for v in range(geo.n_views):
        img1, grads1 = _run(geo, g, scale, geo.angles[v:v + 1], y)
        w = np.zeros((geo.n_views, nv, nu), np.float32)
        w[v] = y
        with monkeypatch.context() as m:
            m.setattr(P, "ROWS_PER_BATCH", 37)    # general path: compaction + host batches
            img3, grads3 = _run(geo, g, scale, geo.angles, w)
        assert img1[0].max() > 0
        np.testing.assert_allclose(img1[0], img3[v], rtol=1e-5, atol=1e-6 * img3[v].max())
        grads3[-1] = grads3[-1][v * n:(v + 1) * n]    # means2d: this view's block
        for name, a, b in zip(("positions", "scales", "rotations", "densities",
                               "density_scale", "means2d"), grads1, grads3):
            assert np.abs(b).max() > 0, name
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max(),
                                       err_msg=f"{name}, view {v}")


def test_voxelizer_float_column_split_equals_integer_split(variant, rng, monkeypatch):
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core import voxelizer as V
    from mi_grg.core.gaussians import Gaussians
    geo, g, scale = _case(rng, n=60)
    block = ([2, 3, 1], [11, 9, 13])
    w = mi.Float(rng.normal(size=11 * 9 * 13).astype(np.float32))

    def run(chunk_pairs=V.DEFAULT_CHUNK_PAIRS):
        leaves = [type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)]
        ds = mi.Float(scale)
        for a in leaves + [ds]:
            dr.enable_grad(a)
        vol = V.voxelize_dr(Gaussians(*leaves), geo, block=block, density_scale=ds,
                            chunk_pairs=chunk_pairs)
        dr.backward(dr.sum(vol.array * w))
        grads = [np.asarray(dr.grad(a), np.float64).ravel() if dr.depth_v(a) == 1 else
                 np.stack([np.asarray(c, np.float64) for c in dr.grad(a)], -1)
                 for a in leaves + [ds]]
        return np.asarray(vol.numpy(), np.float64), grads

    vol_f, grads_f = run()
    vol_c, grads_c = run(chunk_pairs=97)             # many chunks, cut inside boxes
    monkeypatch.setattr(V, "_FLOAT_DIV_MAX", 0)      # integer division everywhere
    vol_i, grads_i = run()
    assert vol_i.max() > 0
    for vol, grads in ((vol_f, grads_f), (vol_c, grads_c)):
        np.testing.assert_allclose(vol, vol_i, rtol=1e-6, atol=1e-7 * vol_i.max())
        for a, b in zip(grads, grads_i):
            assert np.abs(b).max() > 0
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(b).max())



def test_a_new_view_or_block_reuses_the_kernels(variant, rng, kernel_hashes):
    """A training iteration's projection of another view and TV block at another corner
    trace the same kernels: no size that changes with the view or block may enter a kernel
    as a literal. segment_lanes' marker scatter had its lane count in the kernel (a
    comparison, and the LLVM backend's per-thread ReduceMode.Expand copies): every
    projection and block compiled a new kernel (6-8 ms on LLVM, ~20 ms on CUDA) and wrote it
    to the on-disk kernel cache. Checked by kernel hashes, whatever the cache holds."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project_dr
    from mi_grg.core.voxelizer import voxelize_dr
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(20, 28), sDetector=(3.0, 4.0),
                          nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(8))
    n = 300
    q = rng.normal(size=(n, 4))
    g = Gaussians.from_numpy(rng.uniform(-0.7, 0.7, (n, 3)), rng.uniform(0.05, 0.2, (n, 3)),
                             q / np.linalg.norm(q, axis=1, keepdims=True),
                             rng.uniform(0.1, 1.0, n))

    def iteration(view, start):
        raw = g.to_raw()
        for v in raw.values():
            dr.enable_grad(v)
        gg = Gaussians.from_raw(raw)
        means2d = dr.zeros(mi.Vector2f, n)
        dr.enable_grad(means2d)
        img = project_dr(gg, geo, angles=geo.angles[view:view + 1], means2d=means2d)
        vol = voxelize_dr(gg, geo, block=(start, [6, 6, 6]))
        dr.backward(dr.sum(dr.square(img.array)) + dr.sum(dr.square(vol.array)))
        dr.eval(dr.grad(raw["positions"]), dr.grad(raw["raw_densities"]), dr.grad(means2d))
        dr.sync_thread()
        return float(dr.sum(img.array)[0]), float(dr.sum(vol.array)[0])

    traced, sums = [], []
    for view, start in ((0, [1, 2, 3]), (3, [7, 5, 2]), (5, [4, 9, 8]), (6, [9, 0, 6]),
                        (2, [3, 3, 0]), (7, [8, 6, 9])):
        total, hashes = kernel_hashes(lambda: iteration(view, start))
        sums.append(total)
        traced.append(hashes)
    assert len(set(sums)) == len(sums), sums       # the views and blocks really differ
    # Dr.Jit fuses work of equal width into one kernel, so two arrays that happen to share
    # a width make a new fusion now and then (seen: 1 kernel in about 1 run of 5); a size
    # literal makes new kernels on every iteration (3 each with the old segment_lanes).
    new = [len(traced[k] - set().union(*traced[:k])) for k in range(2, len(traced))]
    assert sum(new) <= 1, f"iterations 2.. traced {new} kernel(s) not seen before"
