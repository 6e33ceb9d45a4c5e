"""The recorded training step (TrainConfig.frozen_step, mi_grg.training.frozen_step): the
same loss and gradients as the traced step, re-recorded after a capacity overflow and a
densification, and replayed after a resume."""
import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_grg  # noqa: F401  (first: Dr.Jit's LLVM library and the variant)
from mi_grg.core.gaussians import Gaussians
from mi_grg.data.noise import NoiseModel
from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
from mi_grg.training.config import make_config
from mi_grg.training.frozen_step import FrozenStep
from mi_grg.training.graph import laplacian_loss
from mi_grg.training.losses import projection_loss
from mi_grg.training.trainer import Trainer, laplacian_weight

TINY = dict(n_points=400, max_gaussians=800, eval_every=500, checkpoint_every=20,
            holdout_every=3)


@pytest.fixture(scope="module")
def tiny_case():
    geo = default_geometry(n=16, det=24, views=6)
    return simulate_case("shepp", geo, default_test_angles(2), NoiseModel(), seed=3)


@pytest.fixture
def one_thread():
    """One thread: float atomics then add in one order, so both paths agree bit for bit."""
    threads = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(threads)


def _traced(tr, raw, view):
    """The trainer's traced step (projection, loss, Laplacian, backward): loss, gradients."""
    geo, cfg = tr.case.geometry, tr.cfg
    nv, nu = geo.nDetector
    g = Gaussians.from_raw(raw)
    means2d = dr.zeros(mi.Vector2f, len(g))
    dr.enable_grad(means2d)
    img = tr._project(g, geo.angles[view:view + 1], tr._density_scale, means2d)
    loss = projection_loss(mi.TensorXf(img.array, (nv, nu)), tr.targets[view], cfg.lambda_ssim)
    lap = laplacian_loss(tr.graph, g.densities, normalise=False)
    loss = loss + laplacian_weight(cfg.lambda_lap, len(g)) * lap
    dr.backward(loss)
    grads = {k: np.asarray(dr.grad(v)) for k, v in raw.items()}
    for v in raw.values():
        dr.clear_grad(v)
    return float(loss[0]), grads


def test_frozen_step_equals_traced_and_re_records_on_overflow(tiny_case):
    cfg = make_config("gr", iterations=30, **TINY)
    tr = Trainer(tiny_case, cfg, progress=False)
    raw = {k: dr.detach(v) for k, v in tr.state.raw.items()}
    for v in raw.values():
        dr.enable_grad(v)
    tr._rebuild_graph(raw["positions"])
    said = []
    fz = FrozenStep(tiny_case.geometry, tr.extent, cfg.lambda_ssim, log=said.append)
    n = dr.width(raw["raw_densities"])
    fz.rows_per_gaussian = 0.5          # far too few rows: the first call overflows
    results = []
    for view in (0, 0, 3, 1):
        out, key = fz.run(raw, view, tr.targets[view], tr.graph, tr._density_scale,
                          laplacian_weight(cfg.lambda_lap, n))
        results.append((view, fz.check(out, key), out, key))
    assert results[0][1] is None and all(r[1] is not None for r in results[1:])
    assert len(said) == 1 and "exceed the recorded capacity" in said[0]
    assert fz.fn.n_recordings == 2      # the overflow's and one more, replayed twice
    for view, loss, out, key in results[1:]:
        ref_loss, ref = _traced(tr, raw, view)
        assert loss == pytest.approx(ref_loss, rel=1e-6)
        for k, g in ref.items():
            err = np.abs(np.asarray(out["grads"][k]) - g).max() / np.abs(g).max()
            assert err < 1e-5, (view, k, err)


def _run(case, out_dir, frozen, crash=None, crash_after=None, resume=False, **kw):
    cfg = make_config("gr", iterations=60, seed=5, frozen_step=frozen, **TINY, **kw)
    tr = Trainer(case, cfg, out_dir=out_dir, progress=False, resume=resume)
    if crash is not None:
        crash_after(tr, crash)
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
    assert frozen.frozen.fn.n_recordings >= len(ns)      # one recording per N at least
    assert frozen.frozen.replays >= 20
    assert [r["n_gaussians"] for r in frozen.state.log] == \
        [r["n_gaussians"] for r in traced.state.log]
    np.testing.assert_allclose([r["loss"] for r in frozen.state.log],
                               [r["loss"] for r in traced.state.log], rtol=1e-5)
    a, b = _raw(frozen), _raw(traced)
    for k in a:
        assert np.abs(a[k] - b[k]).max() <= 1e-5 * np.abs(b[k]).max(), k


def test_resumed_frozen_run_replays_like_the_uninterrupted_one(tiny_case, tmp_path,
                                                               crash_after, one_thread):
    full = _run(tiny_case, tmp_path / "full", frozen=True)
    _run(tiny_case, tmp_path / "cut", frozen=True, crash=40, crash_after=crash_after)
    resumed = _run(tiny_case, tmp_path / "cut", frozen=True, resume=True)
    assert resumed.frozen.replays > 0
    assert resumed.state.iteration == full.state.iteration
    a, b = _raw(resumed), _raw(full)
    for k in a:
        assert np.abs(a[k] - b[k]).max() <= 1e-5 * np.abs(b[k]).max(), k
