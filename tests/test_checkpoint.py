"""Checkpoints (mi_grg.training.checkpoint): state objects round-trip, resuming continues the
same run, and checkpoints written by earlier code still load."""
import json
import shutil
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_grg.data.noise import NoiseModel
from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
from mi_grg.training.config import make_config
from mi_grg.training.densify import DensifyConfig, DensifyError, PGADensifier
from mi_grg.protocol.early_stop import EarlyStopper
from mi_grg.training.trainer import Trainer

#: Written by the code of commit 42a14d5 (before checkpoint I/O went through state_dict()):
#: 16^3 shepp (case below), OLD_OPTIONS, crashed after iteration 55; it holds iteration 50,
#: a kept state, the stopper's first evaluation and the densifier's accumulators.
OLD_CHECKPOINT = Path(__file__).parent / "data" / "checkpoint_42a14d5.npz"
# holdout_until=1: the view protocol of 42a14d5 (held out all run; issue 26 came later)
OLD_OPTIONS = dict(iterations=60, seed=5, n_points=120, max_gaussians=800, eval_every=100,
                   checkpoint_every=25, holdout_every=3, holdout_until=1.0, stop_noise=0.0)


@pytest.fixture(scope="module")
def tiny_case():
    geo = default_geometry(n=16, det=24, views=6)
    return simulate_case("shepp", geo, default_test_angles(2), NoiseModel(), seed=3)


def test_densifier_state_round_trip(variant):
    d = PGADensifier(DensifyConfig())
    assert d.state_dict() == {"grad_accum": None, "view_count": None}
    d.accumulate(mi.Float([0.5, 0.0, 2.0]), visible=mi.Bool([True, False, True]))
    d.accumulate(mi.Float([1.0, 3.0, 0.0]))
    st = d.state_dict()
    np.testing.assert_array_equal(st["grad_accum"], [1.5, 3.0, 2.0])
    np.testing.assert_array_equal(st["view_count"], [2.0, 1.0, 2.0])
    e = PGADensifier(DensifyConfig())
    e.load_state_dict(st)
    np.testing.assert_array_equal(np.asarray(e.averaged_gradient()),
                                  np.asarray(d.averaged_gradient()))
    e.accumulate(mi.Float([1.0, 1.0, 1.0]))       # continues from the restored sums
    np.testing.assert_array_equal(np.asarray(e.grad_accum), [2.5, 4.0, 3.0])
    e.load_state_dict({"grad_accum": None, "view_count": None})
    assert e.size is None
    with pytest.raises(DensifyError, match="both"):
        e.load_state_dict({"grad_accum": st["grad_accum"], "view_count": None})


def test_stopper_state_survives_json():
    s = EarlyStopper(drop=0.01, patience=2)
    for it, v in ((100, 20.0), (200, 21.0), (300, 20.5)):
        s.update(it, v)
    t = EarlyStopper(drop=0.01, patience=2)
    t.load_state_dict(json.loads(json.dumps(s.state_dict())))
    assert (t.best, t.best_iteration, t.kept_iteration, t.below) == (21.0, 200, 200, 1)
    # the restored stopper reaches the same verdicts as the original
    assert [t.update(400, 20.5), s.update(400, 20.5)] == ["stop", "stop"]
    assert t.reason == s.reason


class _Views:
    """The trainer's generator, recording the views it draws."""

    def __init__(self, rng):
        self.rng, self.views = rng, []

    def choice(self, *a, **k):
        v = self.rng.choice(*a, **k)
        self.views.append(int(v))
        return v

    def __getattr__(self, name):
        return getattr(self.rng, name)


@pytest.fixture
def one_thread():
    """Dr.Jit's LLVM backend on one thread: float atomics then add in one order, so two runs
    of the same seed agree (with two threads a loaded machine reorders them, and a
    borderline Gaussian can densify in one run and not in the other)."""
    n = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(n)


def test_resume_draws_the_same_views_and_continues_the_loss(tiny_case, tmp_path, crash_after,
                                                             one_thread):
    """A run interrupted at iteration 47 and resumed from its checkpoint (40) trains on the
    same views in the same order as the uninterrupted run, keeps its log and densifier
    statistics (densification at 50 after the resume), and its loss curve continues the
    uninterrupted one (one thread, so float atomics add in one order)."""
    cfg = make_config("gr", iterations=70, seed=2, n_points=200, max_gaussians=800,
                      eval_every=100, checkpoint_every=20, holdout_every=3)
    full = Trainer(tiny_case, cfg, out_dir=tmp_path / "full", progress=False)
    full.rng = _Views(full.rng)
    full.run()

    crash_after(Trainer(tiny_case, cfg, out_dir=tmp_path / "cut", progress=False), 47)
    resumed = Trainer(tiny_case, cfg, out_dir=tmp_path / "cut", progress=False, resume=True)
    assert resumed.state.iteration == 40 and len(resumed.state.log) == 40
    assert resumed.densifier.size == full.state.log[39]["n_gaussians"]
    assert float(dr.sum(resumed.densifier.view_count)[0]) > 0   # statistics since 25
    resumed.rng = _Views(resumed.rng)
    resumed.run()
    assert resumed.rng.views == full.rng.views[40:]
    a = np.array([r["loss"] for r in full.state.log])
    b = np.array([r["loss"] for r in resumed.state.log])
    assert a.shape == b.shape == (70,)
    np.testing.assert_allclose(b, a, rtol=1e-3)
    assert [r["n_gaussians"] for r in resumed.state.log] == \
        [r["n_gaussians"] for r in full.state.log]


def test_checkpoint_of_earlier_code_still_resumes(tiny_case, tmp_path):
    """A checkpoint written before this module existed (automatic fields spelt 0, stopper
    and densifier state in the old keys) resumes: iteration, log, stopper and kept state
    come back, and the run finishes."""
    shutil.copy(OLD_CHECKPOINT, tmp_path / "checkpoint.npz")
    cfg = make_config("gr", **OLD_OPTIONS)
    t = Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False, resume=True)
    assert t.state.iteration == 50 and len(t.state.log) == 50
    assert t.stopper.best_iteration == 50 and t.stopper.kept_iteration == 50
    assert t.state.kept_raw is not None
    with np.load(OLD_CHECKPOINT) as f:
        np.testing.assert_array_equal(t.densifier.state_dict()["grad_accum"], f["dens_grad"])
        assert t.densifier.size == f["raw__raw_densities"].shape[0]
    summary = t.run()
    assert summary["iterations_run"] == 60 and len(t.state.log) == 60
    assert "budget" in summary["stopped_by"]


def test_checkpoint_of_another_config_or_no_checkpoint_is_a_clear_error(tiny_case, tmp_path):
    shutil.copy(OLD_CHECKPOINT, tmp_path / "checkpoint.npz")
    cfg = make_config("gr", **{**OLD_OPTIONS, "graph_s": 0.5, "k": 5})
    with pytest.raises(ValueError, match=r"different config \(differs in \['graph_s', 'k'\]\)"):
        Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False, resume=True)
    # today's default view protocol is not the one the checkpoint's run was made with
    cfg = make_config("gr", **{**OLD_OPTIONS, "holdout_until": 0.75})
    with pytest.raises(ValueError, match=r"differs in \['holdout_until'\]"):
        Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False, resume=True)
    (tmp_path / "checkpoint.npz").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        Trainer(tiny_case, make_config("gr", **OLD_OPTIONS), out_dir=tmp_path,
                progress=False, resume=True)
