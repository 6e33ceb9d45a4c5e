"""The recorded training step (TrainConfig.frozen_step, mi_grg.training.recording): the
same loss and gradients as the traced step, re-recorded after a capacity overflow and a
densification, and replayed after a resume."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_grg  # noqa: F401  (first: Dr.Jit's LLVM library and the variant)
from mi_grg.core.gaussians import Gaussians
from mi_grg.training.config import make_config
from mi_grg.training.recording import Recording
from mi_grg.training.graph import laplacian_loss
from mi_grg.core.voxelizer import voxelize_dr
from mi_grg.training.losses import projection_loss, tv_3d
from mi_grg.training.trainer import Trainer, laplacian_weight

TINY = dict(n_points=400, max_gaussians=800, eval_every=500, checkpoint_every=20,
            holdout_every=3)



@pytest.fixture
def one_thread():
    """One thread: float atomics then add in one order, so both paths agree bit for bit."""
    threads = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(threads)


def _traced(tr, raw, view, start=None):
    """The trainer's traced step (projection, loss, TV block at ``start``, Laplacian,
    backward): loss, gradients."""
    geo, cfg = tr.case.geometry, tr.cfg
    nv, nu = geo.nDetector
    g = Gaussians.from_raw(raw)
    means2d = dr.zeros(mi.Vector2f, len(g))
    dr.enable_grad(means2d)
    img = tr._project(g, geo.angles[view:view + 1], tr._density_scale, means2d)
    loss = projection_loss(mi.TensorXf(img.array, (nv, nu)), tr.targets[view],
                           cfg.losses.lambda_ssim, cfg.losses.data_loss)
    if start is not None:
        block = np.minimum(cfg.losses.tv_block, np.asarray(geo.nVoxel)).tolist()
        vol = voxelize_dr(g, geo, block=(start, block), extent=tr.tv_extent,
                          density_scale=tr._density_scale)
        loss = loss + (cfg.losses.lambda_tv * cfg.losses.tv_every) * tv_3d(vol)
    lap = laplacian_loss(tr.graph, g.densities, normalise=False)
    loss = loss + laplacian_weight(cfg.graph.lambda_lap, len(g)) * lap
    dr.backward(loss)
    grads = {k: np.asarray(dr.grad(v)) for k, v in raw.items()}
    for v in raw.values():
        dr.clear_grad(v)
    return float(loss[0]), grads


def _state(case, **kw):
    """A fresh trainer's state (raw with gradients, graph) and a Recording logging to a
    list."""
    cfg = make_config("gr", iterations=30, **TINY, **kw)
    tr = Trainer(case, cfg, progress=False)
    raw = {k: dr.detach(v) for k, v in tr.state.raw.items()}
    for v in raw.values():
        dr.enable_grad(v)
    tr._rebuild_graph(raw["positions"])
    said = []
    fz = Recording(tr.step_cfg, log=said.append)
    return tr, raw, fz, said


def _frozen_calls(tr, raw, fz, calls):
    out = []
    for view, start in calls:
        res, key = fz.run(tr._step_inputs(raw, view, start))
        out.append((view, start, fz.check(res, key), res))
    return out


def _assert_equal(tr, raw, results):
    for view, start, loss, out in results:
        ref_loss, ref = _traced(tr, raw, view, start)
        assert loss == pytest.approx(ref_loss, rel=1e-6)
        for k, g in ref.items():
            err = np.abs(np.asarray(out["grads"][k]) - g).max() / np.abs(g).max()
            assert err < 1e-5, (view, start, k, err)


def test_frozen_step_equals_traced_and_re_records_on_overflow(tiny_case, one_thread):
    tr, raw, fz, said = _state(tiny_case)
    fz.per_gaussian["rows"] = 0.5       # far too few rows: the first call overflows
    results = _frozen_calls(tr, raw, fz, [(0, None), (0, None), (3, None), (1, None)])
    assert results[0][2] is None and all(r[2] is not None for r in results[1:])
    assert len(said) == 1 and "past the recorded capacity" in said[0]
    assert fz.n_recordings == 2         # the overflow's and one more, replayed twice
    _assert_equal(tr, raw, results[1:])


def test_frozen_tv_iteration_equals_traced(tiny_case, one_thread):
    tr, raw, fz, said = _state(tiny_case, tv_block=8)
    fz.per_gaussian.update(cols=0.1, slices=0.1)     # the first TV call overflows
    results = _frozen_calls(tr, raw, fz, [(2, [4, 0, 8]), (2, [4, 0, 8]), (5, [0, 8, 3]),
                                          (4, None)])
    assert results[0][2] is None and all(r[2] is not None for r in results[1:])
    assert fz.fn[True].n_recordings == 2 and fz.fn[False].n_recordings == 1
    _assert_equal(tr, raw, results[1:])


def test_frozen_rms_step_is_the_views_rms_residual(tiny_case, one_thread):
    """data_loss="rms" (no SSIM, no Laplacian): the recorded step's loss is the root mean
    square of the view's residual, computed here in float64 from its projection; its
    gradients are the traced step's."""
    tr, raw, fz, said = _state(tiny_case, data_loss="rms", lambda_ssim=0.0, lambda_lap=0.0)
    assert tr.step_cfg.data_loss == "rms"
    fz.per_gaussian.update(rows=40.0, near=0.01)
    results = _frozen_calls(tr, raw, fz, [(0, None), (3, None)])
    _assert_equal(tr, raw, results)
    g = Gaussians.from_raw({k: dr.detach(v) for k, v in raw.items()})
    for view, _, loss, _ in results:
        img = np.asarray(tr._project(g, tr.case.geometry.angles[view:view + 1],
                                     tr._density_scale, None).array, np.float64)
        r = img.reshape(-1) - np.asarray(tr.targets[view].array, np.float64)
        assert loss == pytest.approx(np.sqrt(np.mean(r * r)), rel=1e-5)


def _run(case, out_dir, frozen, crash=None, resume=False, **kw):
    """A 60-iteration gr run; ``crash``: interrupted in the iteration after that many."""
    cfg = make_config("gr", iterations=60, seed=5, frozen_step=frozen, **TINY, **kw)
    tr = Trainer(case, cfg, out_dir=out_dir, progress=False, resume=resume)
    if crash is not None:
        step, calls = tr._step, [0]

        def crashing_step(*a):
            calls[0] += 1
            if calls[0] > crash:
                raise KeyboardInterrupt
            return step(*a)
        tr._step = crashing_step
        with pytest.raises(KeyboardInterrupt):
            tr.run()
        return tr
    tr.run()
    return tr


def _raw(tr) -> dict:
    return {k: np.asarray(dr.detach(v)) for k, v in tr.state.raw.items()}


def test_densification_re_records_and_the_run_matches_the_traced_one(tiny_case, tmp_path,
                                                                     one_thread):
    """60 iterations: densification at 25 and 50 changes N, so the step records anew."""
    traced = _run(tiny_case, tmp_path / "t", frozen=False)
    frozen = _run(tiny_case, tmp_path / "f", frozen=True)
    ns = {r["n_gaussians"] for r in frozen.state.log}
    assert len(ns) >= 2                                  # densification happened
    assert frozen.recording.n_recordings >= len(ns)      # one recording per N at least
    assert frozen.recording.replays >= 40 and frozen.recording.fn[True].n_recordings >= 1
    assert [r["n_gaussians"] for r in frozen.state.log] == \
        [r["n_gaussians"] for r in traced.state.log]
    np.testing.assert_allclose([r["loss"] for r in frozen.state.log],
                               [r["loss"] for r in traced.state.log], rtol=1e-5)
    a, b = _raw(frozen), _raw(traced)
    for k in a:
        assert np.abs(a[k] - b[k]).max() <= 1e-5 * np.abs(b[k]).max(), k


def test_resumed_frozen_run_replays_like_the_uninterrupted_one(tiny_case, tmp_path,
                                                               one_thread):
    """Cut at 40 (checkpoint at 40), resumed frozen: as the uninterrupted traced run."""
    full = _run(tiny_case, tmp_path / "full", frozen=False)
    _run(tiny_case, tmp_path / "cut", frozen=True, crash=40)
    resumed = _run(tiny_case, tmp_path / "cut", frozen=True, resume=True)
    assert resumed.recording.replays > 0
    assert resumed.state.iteration == full.state.iteration
    a, b = _raw(resumed), _raw(full)
    for k in a:
        assert np.abs(a[k] - b[k]).max() <= 1e-5 * np.abs(b[k]).max(), k


def test_near_source_records_grow_their_capacity_and_match_traced(tiny_case, one_thread):
    """Two wide Gaussians (scale 0.8, the source 5 away) need the half-line form in every
    view: the first call has no near-source slot (overflow), the next records them."""
    tr, raw, fz, said = _state(tiny_case)
    s = np.stack([np.asarray(c) for c in raw["raw_scales"]], -1)
    s[:2] = np.log(0.8)
    raw["raw_scales"] = mi.Vector3f(*[mi.Float(np.ascontiguousarray(s[:, i])) for i in range(3)])
    dr.enable_grad(raw["raw_scales"])
    fz.per_gaussian["rows"] = 40.0      # rows never overflow here: only the near slots
    results = _frozen_calls(tr, raw, fz, [(1, None), (1, None), (4, None)])
    assert [int(np.asarray(r[3]["counts"][1])[0]) for r in results] == [2, 2, 2]
    assert results[0][2] is None and all(r[2] is not None for r in results[1:])
    assert len(said) == 1 and "near" in said[0]
    _assert_equal(tr, raw, results[1:])
