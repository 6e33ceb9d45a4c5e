"""Chambolle-Pock TV solver (mi_grg.classical.pdhg).

References: NumPy float64 forward differences and the dot-product (adjoint) test for the
gradient / divergence pair; a float64 least-squares solution (explicit matrix of the
Joseph projector, numpy.linalg.lstsq) for lam = 0 on consistent data; the primal-dual gap
of the box-constrained problem, which must fall towards 0.
"""
import numpy as np
import pytest

import mi_grg  # noqa: F401  (before mitsuba)
import mitsuba as mi

from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.core.joseph import JosephProjector, forward_project
from mi_grg.classical.pdhg import (FIXED_LAM, PDHG, divergence, gradient, operator_norm,
                                   pdhg, reconstruct_pdhg, tv_iso)
from mi_grg.evaluation.metrics import psnr_3d


def tiny_geometry(n=6, views=10):
    return Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(12, 12), sDetector=(3.0, 3.0),
                    nVoxel=(n, n, n), sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(views))


def test_gradient_matches_numpy_and_divergence_is_its_negative_adjoint(rng):
    shape = (5, 6, 7)
    x = rng.normal(size=shape)
    p = [rng.normal(size=shape) for _ in range(3)]
    g = [np.array(c.numpy(), np.float64).reshape(shape)
         for c in gradient(mi.Float(x.astype(np.float32).ravel()), shape)]
    for a in range(3):
        ref = np.diff(x, axis=a, append=np.take(x, [-1], axis=a))   # 0 at the far edge
        np.testing.assert_allclose(g[a], ref, atol=1e-5)
    d = np.array(divergence([mi.Float(c.astype(np.float32).ravel()) for c in p],
                            shape).numpy(), np.float64).reshape(shape)
    lhs = sum(np.sum(g[a] * p[a]) for a in range(3))        # <D x, p>
    rhs = -np.sum(x * d)                                     # <x, -div p>
    assert abs(lhs - rhs) <= 1e-5 * (abs(lhs) + np.sqrt(np.sum(x ** 2)) * 10)
    tv = tv_iso(mi.Float(x.astype(np.float32).ravel()), shape)
    assert tv == pytest.approx(np.sum(np.sqrt(sum(gi ** 2 for gi in g))), rel=1e-5)


def _matrix(geo):
    """The Joseph projector as a float64 matrix [pixels, voxels] (one column per voxel)."""
    n = int(np.prod(geo.nVoxel))
    cols = []
    for j in range(n):
        e = np.zeros(n, np.float32)
        e[j] = 1
        cols.append(forward_project(e.reshape(geo.nVoxel), geo).ravel())
    return np.stack(cols, axis=1).astype(np.float64)


def test_operator_norm_matches_svd():
    geo = tiny_geometry(n=4, views=6)
    A = _matrix(geo)
    est = operator_norm(JosephProjector(geo), geo.angles, n_iter=30)
    assert est == pytest.approx(np.linalg.norm(A, 2), rel=1e-3)


def test_lam0_converges_to_least_squares_on_consistent_data(rng):
    geo = tiny_geometry()
    A = _matrix(geo)
    x_true = rng.uniform(0.2, 1.0, A.shape[1])
    b = (A @ x_true).astype(np.float32)
    x_ls = np.linalg.lstsq(A, b.astype(np.float64), rcond=None)[0]
    assert np.linalg.matrix_rank(A) == A.shape[1] and x_ls.min() > 0   # unique, feasible
    err = []
    for n_iter in (30, 600):
        x = pdhg(b.reshape(geo.projection_shape), geo, n_iter=n_iter, lam=0.0, gamma=0.3,
                 progress=False).ravel()
        err.append(np.linalg.norm(x - x_ls) / np.linalg.norm(x_ls))
    assert err[1] < 0.5 * err[0] and err[1] < 2e-2, err


def test_primal_dual_gap_decreases(rng):
    geo = tiny_geometry()
    x_true = np.zeros(geo.nVoxel, np.float32)
    x_true[1:5, 2:5, 1:4] = 1.0
    b = forward_project(x_true, geo) + rng.normal(0, 0.02, geo.projection_shape).astype(
        np.float32)
    s = PDHG(b, geo, np.asarray(geo.angles), lam=0.01, upper=3.0, gamma=0.3)
    gaps = []
    for it in range(400):
        s.step()
        if it in (4, 40, 399):
            gaps.append(s.gap())
    assert all(g > -1e-3 * abs(s.primal()) for g in gaps), gaps      # weak duality
    assert gaps[1] < 0.5 * gaps[0] and gaps[2] < 0.2 * gaps[1], gaps
    assert gaps[2] < 1e-2 * s.primal(), (gaps, s.primal())


def test_contract_and_bad_options(rng):
    from mi_grg.data.case import Case
    geo = tiny_geometry(n=8, views=9)
    x_true = np.zeros(geo.nVoxel, np.float32)
    x_true[2:6, 2:6, 3:5] = 1.0
    case = Case(geometry=geo, train=forward_project(x_true, geo))
    vol, info = reconstruct_pdhg(case, stop="none", n_iter=5, progress=False)
    assert vol.shape == geo.nVoxel and vol.min() >= 0
    assert info == {"protocol": "fixed", "iterations": 5, "lam": FIXED_LAM}
    # with a ground truth the fixed count's 3-D PSNR is logged along the way (the oracle)
    scored = Case(geometry=geo, train=case.train, vol_gt=x_true)
    vol2, info = reconstruct_pdhg(scored, stop="none", n_iter=12, eval_every=5,
                                  progress=False)
    curve = info["oracle"]["curve"]
    assert [s for s, _ in curve] == [5, 10, 12]
    assert curve[-1][1] == pytest.approx(psnr_3d(vol2, x_true), abs=1e-9)
    assert info["oracle"]["psnr_3d_best"] == max(p for _, p in curve)
    assert info["oracle"]["psnr_3d_chosen"] == curve[-1][1]
    np.testing.assert_allclose(vol2, reconstruct_pdhg(case, stop="none", n_iter=12,
                                                         progress=False)[0], atol=1e-5)
    vol, info = reconstruct_pdhg(case, n_iter=20, eval_every=2, lam=[0.0, 0.01],
                                 progress=False)
    assert info["held_out_views"] == [2, 6] and info["final_views"] == list(range(9))
    assert {c["setting"]["lam"] for c in info["candidates"]} == {0.0, 0.01}
    assert info["chosen"]["sweeps"] % 2 == 0 and "oracle" not in info
    assert info["cap"]["iterations"] == 20 and info["cap"]["from"] == "n_iter"
    assert info["cap"]["binds"] == (info["chosen"]["sweeps"] == 20)
    with pytest.raises(ValueError, match="lam"):
        reconstruct_pdhg(case, stop="none", lam=[0.0, 0.1])
    with pytest.raises(ValueError, match="gamma"):
        pdhg(case.train, geo, gamma=0.0)
    with pytest.raises(ValueError, match="widen"):
        reconstruct_pdhg(case, stop="none", widen=True)
    with pytest.raises(ValueError, match="true or false"):
        reconstruct_pdhg(case, widen="yes")
    # widen: n_iter is the cap's base, recorded with the choice
    vol, info = reconstruct_pdhg(case, n_iter=4, eval_every=2, lam=[0.0, 0.01], widen=True,
                                 progress=False)
    assert info["cap"]["base"] == 4 and max(
        c["sweeps_run"] for c in info["candidates"]) >= 4


def test_heldout_cap_grows_with_the_grid():
    from mi_grg.classical.pdhg import HELDOUT_ITERATION_CAP as c60, heldout_cap
    assert c60 == 60
    caps = {n: heldout_cap(tiny_geometry(n=8).replace(nVoxel=n)) for n in
            [(8, 8, 8), (64, 64, 64), (128, 128, 128), (128, 128, 64), (96, 80, 90),
             (256, 256, 256)]}
    assert caps == {(8, 8, 8): 60, (64, 64, 64): 60, (128, 128, 128): 240,
                    (128, 128, 64): 240, (96, 80, 90): 135, (256, 256, 256): 960}
