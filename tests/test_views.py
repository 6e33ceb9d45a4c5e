"""The view protocol (issue 26): held-out views decide, then every view trains."""
import json

import numpy as np
import pytest

import mi_grg
from mi_grg.training.checkpoint import ADDED_LATER
from mi_grg.training.config import ITERATION_RULE, TRAIN_EXTENT, ConfigError, make_config
from mi_grg.training.trainer import Trainer
from mi_grg.protocol.split import MIN_DECISION_VIEWS, holdout_split
from mi_grg.protocol.views import Stop, ViewProtocol, stop_from

# what today's automatic extent and iteration count resolve to, as metrics.json records them
AUTO = {"extent": TRAIN_EXTENT, "iteration_rule": ITERATION_RULE}

TINY = dict(n_points=400, max_gaussians=800, eval_every=500, checkpoint_every=1000,
            holdout_every=3)


def walk(p: ViewProtocol, stop: Stop | None):
    """Replay a schedule as the trainer runs it: (views trained before or at each
    iteration, [(iteration, decision views)]) up to the protocol's end."""
    trained, seen, decisions = [], set(), []
    for it in range(1, p.end(stop) + 1):
        # the stop fires at an evaluation: before it the run does not know of it
        known = stop if stop is not None and it > stop.iteration else None
        seen |= set(p.train_views(it, known).tolist())
        trained.append(set(seen))
        if (it % p.eval_every == 0 or it == p.iterations) and p.decides(it, known):
            decisions.append((it, set(p.held.tolist())))
    return trained, decisions


def random_protocols(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    made = 0
    while made < n:
        iterations = int(rng.integers(1, 250))
        n_views, every = int(rng.integers(2, 30)), int(rng.choice([0, 2, 3, 8]))
        held = len(holdout_split(n_views, every)[1])
        if every and min(held, n_views - held) < MIN_DECISION_VIEWS:
            continue            # a split that cannot decide: an error (tested below)
        made += 1
        p = ViewProtocol(n_views=n_views, holdout_every=every,
                         holdout_until=float(rng.choice([0.0, 1.0, rng.random()])),
                         iterations=iterations, eval_every=int(rng.integers(1, 60)))
        # a stop at any evaluation the window allows, keeping any earlier evaluation
        evals = [i for i in range(p.eval_every, p.window_end + 1, p.eval_every)]
        stop = None
        if evals and rng.random() < 0.6:
            s = int(rng.choice(evals))
            stop = Stop(s, int(rng.choice([e for e in evals if e <= s])))
        yield p, stop


def test_no_decision_uses_a_view_after_it_was_trained():
    """The honesty property over 500 random schedules, with and without a stop."""
    n_decisions = n_joined = 0
    for p, stop in random_protocols(500):
        trained, decisions = walk(p, stop)
        for it, views in decisions:
            assert not views & trained[it - 1], (p, stop, it)
            n_decisions += 1
        end = p.end(stop)
        assert end <= p.iterations                    # the protocol never adds iterations
        if stop is None:
            assert end == p.iterations
        if p.joined(end, stop):
            n_joined += 1
            assert trained[-1] == set(range(p.n_views))   # the result saw every view
    assert n_decisions > 300 and n_joined > 100       # both branches were exercised


def test_window_and_share_after_a_stop():
    p = ViewProtocol(25, 8, 0.75, 1500, 125)
    assert p.held.tolist() == [3, 9, 15, 21] and len(p.fit) == 21
    assert p.window_end == 1125                      # 0.75 x 1500, an evaluation
    assert ViewProtocol(25, 8, 0.75, 3000, 125).window_end == 2250
    assert ViewProtocol(25, 8, 0.8, 1500, 125).window_end == 1125   # rounded down to one
    assert p.decides(1125) and not p.decides(1250)
    assert p.train_views(1125).tolist() == p.fit.tolist()
    assert p.train_views(1126).tolist() == list(range(25))
    # stopped at 1000 keeping 875: 875 x 375 / 1125 = 291.7 -> 292 more on every view
    stop = Stop(1000, 875)
    assert p.after_stop(875) == 292 and p.end(stop) == 1292
    assert p.train_views(1000, stop).tolist() == p.fit.tolist()
    assert len(p.train_views(1001, stop)) == 25 and not p.decides(1125, stop)


def test_holdout_until_one_is_the_old_rule_and_holdout_every_zero_trains_all():
    old = ViewProtocol(25, 8, 1.0, 1500, 125)
    assert old.window_end == 1500 and old.decides(1500)
    assert all(old.train_views(it).tolist() == old.fit.tolist() for it in (1, 1500))
    assert old.after_stop(1000) == 0 and old.end(Stop(1250, 1125)) == 1250
    assert not old.joined(1500)
    none = ViewProtocol(25, 0, 0.75, 1500, 125)
    assert len(none.held) == 0 and none.window_end == 0 and not none.decides(125)
    assert none.train_views(1).tolist() == list(range(25))
    # a split must leave two views to decide on and two to fit; the message names the option
    for n, every in ((3, 1), (8, 8), (25, 30), (3, 2)):
        with pytest.raises(ValueError, match=f"holdout_every={every} leaves"):
            ViewProtocol(n, every, 0.5, 10, 5)
    assert len(ViewProtocol(4, 2, 0.5, 10, 5).held) == 2
    with pytest.raises(ValueError, match="holdout_until"):
        ViewProtocol(25, 8, 1.5, 10, 5)
    with pytest.raises(ConfigError, match="holdout_until"):
        make_config("gr", holdout_until=1.5)


def test_a_run_longer_than_its_horizon_keeps_the_horizons_window():
    """A 3000-iteration run with a 1000-iteration horizon decides and, after a stop, goes on
    exactly as the 1000-iteration run; without a stop its views join where that run's do
    and train every view to 3000."""
    short = ViewProtocol(25, 8, 0.667, 1000, 125)
    long = ViewProtocol(25, 8, 0.667, 3000, 125, horizon=1000)
    assert long.window_end == short.window_end == 625
    assert long.after_stop(500) == short.after_stop(500) == 300
    stop = Stop(625, 500)
    assert long.end(stop) == short.end(stop) == 925 and long.end() == 3000
    assert not long.joined(625) and long.joined(626) and long.joined(3000)
    assert ViewProtocol(25, 8, 0.667, 3000, 125, horizon=5000).window_end == 2000
    assert ViewProtocol(25, 8, 1.0, 3000, 125, horizon=1000).window_end == 3000
    with pytest.raises(ValueError, match="horizon"):
        ViewProtocol(25, 8, 0.667, 3000, 125, horizon=0)


def test_runs_from_before_the_horizon_that_ran_longer_than_the_rule_are_stale():
    """Before ``horizon`` the schedule stretched to the run's count: a run recorded then
    with more iterations than the rule's count is stale, one within it is not."""
    from mi_grg.lab.staleness import stale_keys
    from mi_grg.training.config import iterations_for_size
    cfg = make_config("gr").to_flat()
    del cfg["horizon"]
    rule = iterations_for_size(64)

    def run(planned, config=cfg):
        return {"method": "gr", "options": {}, "nVoxel": [64, 64, 64],
                "method_info": {**AUTO, "config": config, "iterations_planned": planned}}
    assert stale_keys(run(rule)) == [] and stale_keys(run(rule * 3)) == ["horizon"]
    assert stale_keys(run(rule * 3, make_config("gr").to_flat())) == []


def test_stop_from_reads_the_stopper_state():
    assert stop_from(None) is None and stop_from({"reason": None, "history": []}) is None
    st = {"reason": "fell", "history": [[375, 20.0], [500, 19.0]], "kept_iteration": 375}
    assert stop_from(st) == Stop(500, 375)


def test_old_runs_read_as_held_out_all_run():
    """A run recorded before the field existed held its views out all run (1.0), so with
    today's default it is stale (its result would change), named by this key."""
    from mi_grg.lab.staleness import stale_keys
    assert ADDED_LATER["holdout_until"] == 1.0
    cfg = make_config("gr").to_flat()
    del cfg["holdout_until"]
    assert stale_keys({"method": "gr", "options": {}, "method_info": {**AUTO, "config": cfg}}) == \
        ["holdout_until"]
    pinned = {**cfg, "holdout_until": make_config("gr").protocol.holdout_until}
    assert stale_keys({"method": "gr", "options": {}, "method_info": {**AUTO, "config": pinned}}) == []


def test_runs_under_the_old_extent_or_iteration_rule_are_stale():
    """A run that left extent / iterations automatic and recorded no resolved values ran at
    the projector's 4.5 and 1500 x n / 64: stale under today's 3.5 and iteration rule.
    Set explicitly (or planned to a time_budget), the field is the user's and stays."""
    from mi_grg.lab.staleness import stale_keys
    cfg = make_config("gr").to_flat()
    old = {"method": "gr", "options": {}, "method_info": {"config": cfg}}
    assert stale_keys(old) == ["extent", "iterations"]
    assert stale_keys({**old, "method_info": {"config": cfg, **AUTO}}) == []
    assert stale_keys({**old, "method_info": {"config": cfg, **AUTO, "extent": 4.5}}) == \
        ["extent"]
    pinned = make_config("gr", extent=4.5, iterations=1500).to_flat()
    assert stale_keys({"method": "gr", "options": {"extent": 4.5, "iterations": 1500},
                       "method_info": {"config": pinned}}) == []
    budget = make_config("gr", time_budget=300).to_flat()
    assert stale_keys({"method": "gr", "options": {"time_budget": 300},
                       "method_info": {"config": budget, "extent": TRAIN_EXTENT}}) == []


def test_the_window_does_not_make_runs_without_held_out_views_stale():
    """holdout_until / holdout_catch_up act on held-out views only: a holdout_every=0 run
    recorded under another window is current, a run with held-out views is not."""
    from mi_grg.lab.staleness import stale_keys
    for every, want in ((0, []), (8, ["holdout_catch_up", "holdout_until"])):
        cfg = {**make_config("gr", holdout_every=every).to_flat(), "holdout_until": 0.75,
               "holdout_catch_up": True}
        m = {"method": "gr", "options": {"holdout_every": every}, "method_info": {**AUTO, "config": cfg}}
        assert stale_keys(m) == want


def test_the_refinements_options_do_not_make_runs_without_it_stale():
    """The refinement's and the fit back's options act only with refine="tv": an r2 run
    recorded under another fit_iterations is current, a gr run is not."""
    from mi_grg.lab.staleness import stale_keys
    for method, want in (("r2", []), ("gr", ["fit_iterations", "fit_rate_scale"])):
        cfg = {**make_config(method).to_flat(), "fit_iterations": 300, "fit_rate_scale": 1.0}
        m = {"method": method, "options": {}, "method_info": {**AUTO, "config": cfg}}
        assert stale_keys(m) == want


def test_a_wider_stop_margin_leaves_runs_that_never_stopped_current():
    """stop_noise only widens the margin: a run recorded without it (0) that never stopped and
    returned its last state is current; one that stopped, or that returned a kept state, or
    that ran with a wider margin than today's, runs again."""
    from mi_grg.lab.staleness import stale_keys
    cfg = {k: v for k, v in make_config("gr").to_flat().items() if k != "stop_noise"}

    def run(stop, returned, used=None):
        c = cfg if used is None else {**cfg, "stop_noise": used}
        return {"method": "gr", "options": {}, "n_train_views": 25,
                "method_info": {**AUTO, "config": c, "iterations_run": 1500,
                                "views": {"stop": stop, "returned_state_iteration": returned}}}
    assert stale_keys(run(None, 1500)) == []
    assert stale_keys(run({"iteration": 1125, "kept_iteration": 875}, 1417)) == ["stop_noise"]
    assert stale_keys(run(None, 1375)) == ["stop_noise"]       # held out all run: kept state
    assert stale_keys(run(None, 1500, used=4.0)) == ["stop_noise"]


def test_runs_with_the_old_split_are_stale():
    """Runs that held out views 0, 8, 16, 24 (the split before f3bf235) run again; runs with
    today's split, or that record no held-out views, do not."""
    from mi_grg.lab.staleness import stale_keys
    cfg = make_config("gr").to_flat()
    gr = {"method": "gr", "options": {}, "n_train_views": 25,
          "method_info": {**AUTO, "config": cfg, "held_out_views": [0, 8, 16, 24]}}
    assert stale_keys(gr) == ["held_out_views"]
    gr["method_info"]["held_out_views"] = [3, 9, 15, 21]
    assert stale_keys(gr) == []
    sart = {"method": "sart", "options": {}, "n_train_views": 25,
            "method_info": {"protocol": "heldout", "held_out_views": [0, 8, 16, 24],
                            "stop_rule": {"holdout_every": 8, "noise": 3.0}}}
    assert stale_keys(sart) == ["held_out_views"]
    sart["method_info"]["held_out_views"] = [3, 9, 15, 21]
    assert stale_keys(sart) == []
    # decided before the scatter margin (its rule records no noise): run again
    del sart["method_info"]["stop_rule"]["noise"]
    assert stale_keys(sart) == ["stop_noise"]
    assert stale_keys({"method": "fdk", "options": {}, "n_train_views": 25}) == []


# ---------------------------------------------------------------------------- in training

def spy_views(t: Trainer, monkeypatch):
    """Record (iteration, trained view) and (iteration, evaluated views) of a run: a spy
    on the step's inputs, which name the drawn view (the refit's name a density scale)."""
    trained, evaluated = [], []
    real_inputs = t._step_inputs

    def step_inputs(raw, view, start=None, **kw):
        if not kw:
            trained.append((t.state.iteration + 1, view))
        return real_inputs(raw, view, start, **kw)
    real_heldout = t._heldout_psnr

    def heldout(raw):
        evaluated.append((t.state.iteration, t.held_idx.tolist()))
        return real_heldout(raw)
    monkeypatch.setattr(t, "_step_inputs", step_inputs)
    monkeypatch.setattr(t, "_heldout_psnr", heldout)
    return trained, evaluated


def test_training_run_records_the_views(tiny_case, monkeypatch, tmp_path):
    """250 iterations, evaluations every 125, window 0.5 x 250 = 125: views 1 and 4 decide at
    125 and train from 126; metrics.json says so."""
    t = Trainer(tiny_case, make_config("gr", iterations=250, holdout_until=0.5, **TINY),
                progress=False)
    trained, evaluated = spy_views(t, monkeypatch)
    info = t.run()
    assert evaluated == [(125, [1, 4])]
    assert {v for it, v in trained if it <= 125} <= {0, 2, 3, 5}
    assert {v for it, v in trained if it > 125} == set(range(6))   # seed-fixed draw
    assert len(trained) == 250
    _, m = mi_grg.reconstruct(tiny_case, "gr", out_dir=tmp_path, iterations=250,
                              holdout_until=0.5, progress=False, **TINY)
    info_m = json.loads((tmp_path / "metrics.json").read_text())["method_info"]
    views = info_m["views"]
    assert views["held_out_views"] == [1, 4] and views["decision_window_end"] == 125
    # one evaluation: too few to measure a scatter, so the margin is 0.5 % of the best
    margin = info_m["stop_margin"]
    assert (margin["drop"], margin["noise"], margin["scatter_db"]) == (0.005, 3.0, 0.0)
    assert margin["margin_db"] == pytest.approx(0.005 * views["decisions"][0]["heldout_psnr"])
    # densification ends at 125 here, so that evaluation is judged
    assert [(d["iteration"], d["views"]) for d in views["decisions"]] == [(125, [1, 4])]
    assert views["held_out_views_trained_from"] == 126
    assert views["iterations_on_all_views"] == 125 and views["returned_state_iteration"] == 250
    assert views["trained_on_views"] == list(range(6)) and views["stop"] is None


def test_a_stop_goes_on_from_the_kept_state_on_every_view(tiny_case, monkeypatch):
    """750 iterations, window 0.8 x 750 -> 500: judged at 375 (best) and 500 (a drop,
    patience 1: stop). The state of 375 goes on for 375 x 250 / 500 = 188 iterations on
    every view, and no held-out view is evaluated after it was trained."""
    t = Trainer(tiny_case, make_config("gr", iterations=750, stop_patience=1,
                                       holdout_until=0.8, **TINY), progress=False)
    trained, evaluated = spy_views(t, monkeypatch)
    scores = iter([20.0, 20.0, 20.0, 18.0])
    real_heldout = t._heldout_psnr
    monkeypatch.setattr(t, "_heldout_psnr", lambda raw: (real_heldout(raw), next(scores))[1])
    seen, stepped = {}, {}
    real_update, real_step = t.stopper.update, t._step

    def spy(it, value):
        seen[it] = np.asarray(t.state.raw["raw_densities"]).copy()
        return real_update(it, value)

    def step(it, raw, *a, **k):     # the state each iteration starts from
        stepped[it] = np.asarray(raw["raw_densities"]).copy()
        return real_step(it, raw, *a, **k)
    monkeypatch.setattr(t.stopper, "update", spy)
    monkeypatch.setattr(t, "_step", step)
    info = t.run()
    assert [it for it, _ in evaluated] == [125, 250, 375, 500]
    first = min(it for it, v in trained if v in (1, 4))
    assert first > 500 and all(it < first for it, _ in evaluated)
    v = info["views"]
    assert v["stop"]["iteration"] == 500 and v["stop"]["kept_iteration"] == 375
    assert info["iterations_run"] == 500 + 188 == v["returned_state_iteration"]
    assert v["held_out_views_trained_from"] == 501 and v["iterations_on_all_views"] == 188
    assert "then 188 iterations on every view" in info["stopped_by"]
    # the continuation started from the kept state (375), not from the state of 500
    np.testing.assert_array_equal(stepped[501], seen[375])
    assert not np.array_equal(seen[375], seen[500])
    assert not np.array_equal(np.asarray(t.state.raw["raw_densities"]), seen[375])


def test_a_longer_run_follows_the_horizons_schedule_then_anneals(tiny_case, one_thread):
    """iterations=240 with horizon=120: the schedule (densification window, evaluations,
    held-out window) is the 120-iteration run's, the learning rate keeps decaying past 120,
    and the first 120 iterations are that run's (one thread, so float atomics add in one
    order: with two on a loaded machine a borderline Gaussian can densify in one run only)."""
    short = Trainer(tiny_case, make_config("gr", iterations=120, **TINY), progress=False)
    long = Trainer(tiny_case, make_config("gr", iterations=240, horizon=120, **TINY),
                   progress=False)
    assert long.sched == short.sched and long.views.window_end == short.views.window_end
    lr0 = long.optimizer.lr0["positions"]
    assert long.optimizer.lr("positions", 240) == pytest.approx(0.01 * lr0, rel=1e-9)
    stretched = Trainer(tiny_case, make_config("gr", iterations=240, horizon=240, **TINY),
                        progress=False)
    assert stretched.sched != short.sched
    states = {}
    real = long._step

    def step(it, raw, *a, **k):
        if it == 121:
            states["long"] = np.asarray(raw["raw_densities"]).copy()
        return real(it, raw, *a, **k)
    long._step = step
    info = long.run()
    short.run()
    assert info["iterations_run"] == 240
    assert info["schedule"]["horizon"] == 120 and info["schedule"]["scaled_to"] == 120
    np.testing.assert_allclose(states["long"], np.asarray(short.state.raw["raw_densities"]),
                               rtol=1e-3, atol=1e-4)


def test_holdout_every_zero_still_trains_on_every_view(tiny_case, monkeypatch):
    t = Trainer(tiny_case, make_config("gr", iterations=60, **{**TINY, "holdout_every": 0}),
                progress=False)
    trained, evaluated = spy_views(t, monkeypatch)
    info = t.run()
    assert len(trained) == 60 and {v for _, v in trained} == set(range(6))
    assert evaluated == []
    assert info["views"]["trained_on_views"] == list(range(6))
    assert info["views"]["decisions"] == [] and info["views"]["held_out_views"] == []


def expected_draws(p: ViewProtocol, stop: Stop | None) -> np.ndarray:
    """Each view's expected number of training draws over the run, [n_views] float64, summed
    iteration by iteration (a uniform draw unless ``draw_weights`` says otherwise); after a
    stop the count restarts from the kept state's."""
    draws = np.zeros(p.n_views)
    for it in range(1, p.end(stop) + 1):
        known = stop if stop is not None and it > stop.iteration else None
        if stop is not None and it == stop.iteration + 1:
            draws[:] = 0.0                  # back to the kept state: replay its draws
            for j in range(1, stop.kept_iteration + 1):
                draws[p.train_views(j, None)] += 1.0 / len(p.train_views(j, None))
        views = p.train_views(it, known)
        w = p.draw_weights(it, known)
        draws[views] += (np.full(len(views), 1.0 / len(views)) if w is None else w)
    return draws


def test_catch_up_equalises_the_expected_draws():
    """Over random schedules: the weights are a distribution over the views the step draws
    from; with enough iterations after the join every view's expected draws are equal at the
    end; with too few, the held-out views take every draw and stay behind."""
    n_equal = n_short = 0
    for p0, stop in random_protocols(600, seed=1):
        p = ViewProtocol(p0.n_views, p0.holdout_every, p0.holdout_until, p0.iterations,
                         p0.eval_every, catch_up=True)
        for it in range(1, p.end(stop) + 1):
            known = stop if stop is not None and it > stop.iteration else None
            w = p.draw_weights(it, known)
            if w is None:
                assert not p.joined(it, known)
                continue
            assert w.shape == p.train_views(it, known).shape and np.all(w >= 0)
            assert abs(w.sum() - 1.0) < 1e-12
        if not p.joined(p.end(stop), stop):
            continue
        d = expected_draws(p, stop)
        held, fit = d[p.held], d[p.fit]
        if held.min() < fit.min() - 1e-9:           # too few iterations after the join
            n_short += 1
            kept = stop.kept_iteration if stop else p.window_end
            assert np.allclose(fit, kept / len(p.fit))   # fit views not drawn after it
        else:
            n_equal += 1
            assert np.allclose(d, d.mean()), (p, stop, d)
    assert n_equal > 30 and n_short > 10


def test_catch_up_run_draws_the_held_out_views_more_often(tiny_case, monkeypatch):
    """6 views, 1 and 4 held out to iteration 150 of 300: before the join 37.5 expected draws
    per fit view; over the 150 after it the weights are 1/12 (fit) and 1/3 (held) per view,
    so that each view ends at 300 / 6 = 50. The run's draws after the join follow them."""
    cfg = make_config("gr", iterations=300, holdout_until=0.5, holdout_catch_up=True,
                      **dict(TINY, eval_every=150))
    t = Trainer(tiny_case, cfg, progress=False)
    assert t.views.draw_weights(150) is None
    np.testing.assert_allclose(t.views.draw_weights(151), [1, 4, 1, 1, 4, 1] / np.float64(12))
    trained, _ = spy_views(t, monkeypatch)
    info = t.run()
    after = np.bincount([v for it, v in trained if it > 150], minlength=6)
    assert after.sum() == 150
    # the two held-out views together: binomial(150, 2/3), 100 +- 5.8 (uniform: 50)
    assert 82 <= after[[1, 4]].sum() <= 118, after
    assert info["views"]["catch_up"] is True
