"""Checkpoints (mi_grg.training.checkpoint): state objects round-trip, resuming continues the
same run, and checkpoints written by earlier code still load."""
import json
import shutil
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_grg.training.config import make_config
from mi_grg.training.densify import DensifyError, PGADensifier
from mi_grg.protocol.early_stop import EarlyStopper
from mi_grg.training.trainer import Trainer

#: Written by the code of commit 42a14d5 (before checkpoint I/O went through state_dict()):
#: 16^3 shepp (case below), OLD_OPTIONS, crashed after iteration 55; it holds iteration 50,
#: a kept state, the stopper's first evaluation and the densifier's accumulators.
OLD_CHECKPOINT = Path(__file__).parent / "data" / "checkpoint_42a14d5.npz"
# holdout_until=1: the view protocol of 42a14d5 (held out all run; issue 26 came later)
OLD_OPTIONS = dict(iterations=60, seed=5, n_points=120, max_gaussians=800, eval_every=100,
                   checkpoint_every=25, holdout_every=3, holdout_until=1.0, stop_noise=0.0)



def test_densifier_state_round_trip(variant):
    d = PGADensifier()
    assert d.state_dict() == {"grad_accum": None, "view_count": None}
    d.accumulate(mi.Float([0.5, 0.0, 2.0]), visible=mi.Bool([True, False, True]))
    d.accumulate(mi.Float([1.0, 3.0, 0.0]))
    st = d.state_dict()
    np.testing.assert_array_equal(st["grad_accum"], [1.5, 3.0, 2.0])
    np.testing.assert_array_equal(st["view_count"], [2.0, 1.0, 2.0])
    e = PGADensifier()
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


def test_raw_parameters_reads_a_checkpoints_states_checked(tmp_path):
    """raw_parameters gives the file's last and kept states as Dr.Jit arrays (compared with
    numpy's reading of the same file), None for a kept state the file lacks, and refuses
    what a resume refuses."""
    from mi_grg.training.checkpoint import raw_parameters
    with np.load(OLD_CHECKPOINT) as f:
        arrays = dict(f)
    for which in ("raw", "kept"):
        got = raw_parameters(OLD_CHECKPOINT, which)
        assert set(got) == {"positions", "raw_scales", "raw_rotations", "raw_densities"}
        for k, v in got.items():
            a = np.stack([np.asarray(c) for c in v], -1) if dr.depth_v(v) > 1 else np.asarray(v)
            np.testing.assert_array_equal(a, arrays[f"{which}__{k}"])
    no_kept = tmp_path / "no_kept.npz"
    np.savez(no_kept, **{k: v for k, v in arrays.items() if not k.startswith("kept")})
    assert raw_parameters(no_kept, "kept") is None
    assert raw_parameters(no_kept)["raw_densities"].shape == (arrays["raw__raw_densities"].size,)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{**arrays, "raw__raw_densities": np.full_like(arrays["raw__raw_densities"],
                                                                  np.nan)})
    with pytest.raises(ValueError, match="raw__raw_densities"):
        raw_parameters(bad)
    with pytest.raises(ValueError, match="which must be"):
        raw_parameters(OLD_CHECKPOINT, "best")


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


def test_a_resume_under_another_automatic_rule_is_refused(tiny_case, tmp_path, crash_after,
                                                            monkeypatch):
    """An interrupted run whose iteration count was automatic resumes while the rule gives
    the count it started with; once the rule gives another (new code), resuming would finish
    one count's schedule with another's: the trainer refuses, naming the field and both
    counts, and the runner starts the run afresh (``lab.staleness.resumes``)."""
    import mi_grg.training.checkpoint as ck
    import mi_grg.training.schedule as schedule
    from mi_grg.lab.staleness import resumes
    opts = dict(seed=2, n_points=200, max_gaussians=800, checkpoint_every=10, holdout_every=3)
    cfg = make_config("gr", **opts)
    assert cfg.schedule.iterations is None and cfg.schedule.extent is None
    crash_after(Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False), 12)
    ckpt = tmp_path / "checkpoint.npz"
    assert resumes("gr", opts, ckpt, None)
    assert Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False,
                   resume=True).state.iteration == 10
    rule = ck.iterations_for_size
    for module in (ck, schedule):
        monkeypatch.setattr(module, "iterations_for_size", lambda n: rule(n) + 100)
    then = rule(max(tiny_case.geometry.nVoxel))
    with pytest.raises(ValueError, match=rf"iterations \(automatic: {then} then, "
                                         rf"{then + 100} now\)"):
        Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False, resume=True)
    assert not resumes("gr", opts, ckpt, None)


# The bit-for-bit resume checks: a run long enough to densify after the interruption and
# to end on every view (the returned state is the last one).
EXACT = dict(iterations=70, seed=2, n_points=200, max_gaussians=800, eval_every=100,
             holdout_every=3)


def _one_thread_run(trainer):
    n = dr.thread_count()
    dr.set_thread_count(1)
    try:
        return trainer.run()
    finally:
        dr.set_thread_count(n)


@pytest.fixture(scope="module")
def uninterrupted(tiny_case, tmp_path_factory):
    """The reference: EXACT run to its end without a stop, on one thread."""
    out = tmp_path_factory.mktemp("uninterrupted")
    t = Trainer(tiny_case, make_config("gr", **EXACT), out_dir=out, progress=False)
    _one_thread_run(t)
    return t, out


def _assert_same_state(a, b):
    """Every raw parameter, Adam's moments and step counts, the densifier's statistics and
    the generator: equal bit for bit."""
    assert a.state.iteration == b.state.iteration
    for k in a.state.raw:
        np.testing.assert_array_equal(np.asarray(b.state.raw[k]), np.asarray(a.state.raw[k]),
                                      err_msg=k)
    oa, ob = a.optimizer.state_dict(), b.optimizer.state_dict()
    assert sorted(oa) == sorted(ob)
    for name in oa:
        assert oa[name]["step"] == ob[name]["step"], name
        np.testing.assert_array_equal(ob[name]["m"], oa[name]["m"], err_msg=name)
        np.testing.assert_array_equal(ob[name]["v"], oa[name]["v"], err_msg=name)
    da, db = a.densifier.state_dict(), b.densifier.state_dict()
    for k in da:
        np.testing.assert_array_equal(db[k], da[k], err_msg=k)
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


def test_resumed_run_equals_the_uninterrupted_one_bit_for_bit(tiny_case, tmp_path, crash_after,
                                                              uninterrupted, one_thread):
    """Crashed in iteration 48 (mid-step, so the checkpoint of 40 is what survives) and
    resumed to the end: every parameter, Adam's moments and the densifier's statistics
    equal the uninterrupted run's exactly (one thread: float atomics in one order)."""
    full, _ = uninterrupted
    cfg = make_config("gr", **EXACT, checkpoint_every=20)
    crash_after(Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False), 47)
    # the interval is bookkeeping: resuming with another one continues the same run
    resumed = Trainer(tiny_case, make_config("gr", **EXACT, checkpoint_every=9),
                      out_dir=tmp_path, progress=False, resume=True)
    assert resumed.state.iteration == 40
    resumed.run()
    assert resumed.state.iteration == 70
    _assert_same_state(full, resumed)


def test_ctrl_c_finishes_the_iteration_and_leaves_a_checkpoint_that_resumes(
        tiny_case, tmp_path, uninterrupted, one_thread, sigint_raises):
    """SIGINT during iteration 45 (the automatic interval of this 70-iteration run is 7, so
    the last periodic checkpoint is 42): the iteration finishes, a checkpoint of 45 is
    written, KeyboardInterrupt follows and the handler before the run is back. Resumed
    through ``reconstruct``, the run ends as the uninterrupted one, bit for bit, and
    metrics.json's seconds add the interrupted call's wall clock."""
    import json
    import os
    import signal
    from mi_grg.methods import reconstruct
    from mi_grg.training.checkpoint import CHECKPOINT_NAME
    full, full_out = uninterrupted
    cfg = make_config("gr", **EXACT)
    cut = Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False)
    step = cut._step

    def interrupted_step(it, raw):
        if it == 45:
            os.kill(os.getpid(), signal.SIGINT)
        return step(it, raw)
    cut._step = interrupted_step
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        cut.run()
    assert signal.getsignal(signal.SIGINT) is before
    with np.load(tmp_path / CHECKPOINT_NAME) as f:
        arrays = dict(f)
    meta = json.loads(bytes(arrays["meta"]).decode())
    assert meta["iteration"] == 45 and len(meta["log"]) == 45
    assert meta["wall_seconds"] >= meta["seconds"] > 0
    # an earlier call that took 1000 s: the resumed run's seconds must include it
    meta["wall_seconds"] = 1000.0
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(tmp_path / CHECKPOINT_NAME, **arrays)

    n = dr.thread_count()
    _, metrics = reconstruct(tiny_case, "gr", out_dir=tmp_path, resume=True, progress=False,
                             **EXACT)
    assert dr.thread_count() == n
    info = metrics["method_info"]
    assert info["init"] == {"resumed_from": 45} and info["iterations_run"] == 70
    assert info["resumed_seconds"] == 1000.0 and 1000.0 < metrics["seconds"] < 1000.0 + 600
    assert info["checkpoint_every"] == 7
    with np.load(full_out / CHECKPOINT_NAME) as a, np.load(tmp_path / CHECKPOINT_NAME) as b:
        keys = [k for k in a.files if k != "meta"]
        assert sorted(keys) == sorted(k for k in b.files if k != "meta")
        assert any(k.startswith("adam_m__") for k in keys)
        for k in keys:
            np.testing.assert_array_equal(b[k], a[k], err_msg=k)


def test_checkpoint_interval_scales_with_the_run():
    from mi_grg.training.trainer import checkpoint_interval
    assert [checkpoint_interval(None, n) for n in (5, 60, 999, 4000, 6000, 30000)] == \
        [1, 6, 99, 400, 500, 500]
    assert checkpoint_interval(25, 60) == 25 and checkpoint_interval(1000, 60) == 1000


def test_restored_state_does_not_alias_the_files_arrays(variant):
    """Dr.Jit maps a contiguous NumPy array rather than copying it; what a checkpoint
    restores (parameters, Adam moments, densifier sums) must hold its own memory, so that
    writing to (or freeing) the arrays read from the file changes nothing."""
    from mi_grg.training.checkpoint import _raw_from_numpy
    from mi_grg.training.optim import Adam
    arrs = {"positions": np.ones((4, 3), np.float32), "raw_scales": np.ones((4, 3), np.float32),
            "raw_rotations": np.ones((4, 4), np.float32), "raw_densities": np.ones(4, np.float32)}
    raw = _raw_from_numpy(arrs)
    opt = Adam({k: 1e-3 for k in arrs})
    moments = {"raw_densities": {"m": np.full(4, 2.0, np.float32),
                                 "v": np.full(4, 3.0, np.float32), "step": 1}}
    opt.load_state_dict(moments, like=raw)
    dens = PGADensifier()
    sums = {"grad_accum": np.full(4, 5.0, np.float32), "view_count": np.full(4, 6.0, np.float32)}
    dens.load_state_dict(sums)
    for a in (*arrs.values(), moments["raw_densities"]["m"], moments["raw_densities"]["v"],
              *sums.values()):
        a[...] = -7.0
    np.testing.assert_array_equal(np.asarray(raw["raw_densities"]), 1.0)
    np.testing.assert_array_equal(np.asarray(opt.state["raw_densities"].m), 2.0)
    np.testing.assert_array_equal(np.asarray(opt.state["raw_densities"].v), 3.0)
    np.testing.assert_array_equal(np.asarray(dens.grad_accum), 5.0)
    np.testing.assert_array_equal(np.asarray(dens.view_count), 6.0)
