"""Training to a wall-clock budget (TrainConfig.run.time_budget, mi_grg.training.budget):
the plan's arithmetic against brute force, the probe leaving the run untouched, the deadline,
resuming, and the errors that name the option."""
import dataclasses

import numpy as np
import pytest

from mi_grg.training import budget
from mi_grg.training.budget import (MIN_ITERATIONS, REPLAN_SHARE, LoopPace, ProbeCosts,
                                    TimeBudgetError, loop_seconds, make_plan, measured_pace,
                                    plan_iterations, replan, replans_done, replans_of,
                                    rest_seconds)
from mi_grg.training.config import ConfigError, make_config, read_config_xml
from mi_grg.training.densify import DensifyWindow, PGADensifier
from mi_grg.training.optim import Adam, AdamError
from mi_grg.training.trainer import Trainer, _scaled

TINY = dict(n_points=400, max_gaussians=800, eval_every=500, checkpoint_every=1000,
            holdout_every=3)


# ---------------------------------------------------------------------------- the arithmetic
@pytest.mark.parametrize("iterations", [50, 77, 500, 1500, 3001])
def test_loop_seconds_counts_what_the_loop_does(iterations):
    """The price is the probe's costs times the loop's counts: iterations before / after
    densification starts, the densifier's own densify iterations, the evaluations."""
    cfg = make_config("gr")
    s = _scaled(cfg, iterations)
    dens = PGADensifier(cfg.densify, window=DensifyWindow(
        start=s["densify_start"], stop=s["densify_stop"], interval=s["densify_interval"]))
    n_dens = sum(dens.is_densify_iteration(it) for it in range(1, iterations + 1))
    window = iterations // 2
    n_eval = sum(1 for it in range(1, window + 1) if it % s["eval_every"] == 0) + 1
    pre = min(iterations, s["densify_start"])
    costs = ProbeCosts(step=0.1, evaluation=0.3, rebuild=0.7, n=1000, cap=2500, log_3d=0.9)
    want = pre * 0.1 + (iterations - pre) * 0.25 + n_dens * 1.75 + n_eval * 0.75
    assert loop_seconds(iterations, s, window, costs) == pytest.approx(want)
    assert loop_seconds(iterations, s, window, costs, logs_3d=7) == pytest.approx(
        want + 7 * 0.9 * 2.5)
    # a cap below the probe's count never makes an iteration cheaper than the probe's
    low = dataclasses.replace(costs, cap=10)
    assert loop_seconds(iterations, s, window, low) == pytest.approx(
        iterations * 0.1 + n_dens * 0.7 + n_eval * 0.3)


@pytest.mark.parametrize("loop_budget", [4.0, 5.0, 37.3, 250.0, 1e4])
def test_plan_is_the_largest_count_that_fits(loop_budget):
    def price(i):            # a step-shaped, non-decreasing price (like the real one)
        return 0.05 * i + 0.5 * (i // 97)
    got = plan_iterations(loop_budget, price)
    fits = [i for i in range(MIN_ITERATIONS, 300000) if price(i) <= loop_budget]
    assert got == (max(fits) if fits else None)


@pytest.mark.parametrize("remaining", [0.01, 3.0, 41.0, 900.0])
def test_replan_is_the_largest_rest_that_fits(remaining):
    def price_rest(i):        # iterations after 400 at 0.1 s, evaluations every 50 at 0.4 s
        return (i - 400) * 0.1 + ((i - 400) // 50 + 1) * 0.4
    got = replan(400, remaining, price_rest)
    fits = [i for i in range(401, 100000) if price_rest(i) <= REPLAN_SHARE * remaining]
    assert got == (max(fits) if fits else 401)


@pytest.mark.parametrize("growth,stop,iterations", [(0.0, 300, 900), (40.0, 300, 900),
                                                   (40.0, 2000, 1500), (900.0, 700, 1200),
                                                   (40.0, 300, 251)])
def test_rest_seconds_against_an_iteration_by_iteration_count(growth, stop, iterations):
    """The rest's price against a loop that grows the count at every iteration of the open
    window (capped), pays each step, each densification and each evaluation at the count."""
    pace = LoopPace(at=250, per_gaussian=2e-6, n=60000, growth=growth, cap=400000,
                    rebuild=1e-5, evaluation=3e-6, log_3d=5e-5)
    events = range(275, min(stop, iterations + 1), 25)
    n, total = float(pace.n), 0.0
    for t in range(pace.at + 1, iterations + 1):
        if t <= stop:
            n = min(pace.cap, n + growth)
        total += pace.per_gaussian * n + (pace.rebuild * n if t in events else 0.0)
    total += (4 * pace.evaluation + 3 * pace.log_3d) * n
    assert rest_seconds(pace, iterations, stop, events, 4, 3) == pytest.approx(total, rel=1e-9)


def test_replans_of_reads_a_plan_written_before_the_window_replans():
    old = {"iterations": 90, "replanned": {"at": 45, "iterations": 110}}
    assert replans_of(old) == [{"at": 45, "iterations": 110, "final": True}]
    assert replans_done(old) and not replans_done({"replans": [{"at": 5, "final": False}]})
    assert replans_of(None) == []


def test_measured_pace_leaves_out_the_priced_steps_and_keeps_every_other():
    # TV every other step; an evaluation and a densification step, priced apart
    steps = [0.1, 0.15] * 20 + [2.0, 0.1, 0.15, 5.0]
    clock = np.concatenate([[0.0], np.cumsum(steps)]).tolist()
    apart = [False] * 40 + [True, False, False, True]
    assert measured_pace(clock, apart) == pytest.approx(0.125, rel=1e-9)
    # A TV step at 4x a plain one (a GPU whose plain step is a few ms): every TV step
    # belongs to the pace (a filter by size, steps over 3x the median left out, gave 0.025)
    gpu = [0.025, 0.1] * 20 + [0.025, 0.025]
    clock = np.concatenate([[0.0], np.cumsum(gpu)]).tolist()
    assert measured_pace(clock, [False] * len(gpu)) == pytest.approx(np.mean(gpu), rel=1e-9)
    assert measured_pace(clock) == pytest.approx(np.mean(gpu), rel=1e-9)
    with pytest.raises(ValueError):
        measured_pace([1.0])
    with pytest.raises(ValueError, match="priced_apart"):
        measured_pace([0.0, 1.0, 2.0], [False])


def test_adam_rehorizon_continues_the_decay_without_a_jump():
    a, ref = Adam(max_steps=1000), Adam(max_steps=1000)
    a.rehorizon(400, 1600)
    for t in (0, 1, 200, 400):              # before the knot: unchanged
        assert a.lr("positions", t) == pytest.approx(ref.lr("positions", t), rel=1e-12)
    lr0 = ref.lr0["positions"]
    assert a.lr("positions", 1600) == pytest.approx(0.1 * lr0, rel=1e-12)
    assert a.lr("positions", 5000) == pytest.approx(0.1 * lr0, rel=1e-12)
    # log-linear between the knot and the new end, continuous at the knot
    e = [np.log(a.lr("positions", t) / lr0) for t in (400, 700, 1000, 1600)]
    d = np.diff(e)                          # steps of 300, 300, 600 iterations
    assert d[0] == pytest.approx(d[1]) and d[2] == pytest.approx(2 * d[0])
    assert e[0] == pytest.approx(np.log(ref.lr("positions", 400) / lr0))
    shorter = Adam(max_steps=1000)
    shorter.rehorizon(400, 500)             # a shorter run decays faster, still from 400
    assert shorter.lr("raw_densities", 500) == pytest.approx(0.1 * shorter.lr0["raw_densities"])
    lr_800 = a.lr("positions", 800)
    a.rehorizon(800, 2000)                  # a second move: continuous again, ends at 2000
    assert a.lr("positions", 800) == pytest.approx(lr_800, rel=1e-12)
    assert a.lr("positions", 2000) == pytest.approx(0.1 * lr0, rel=1e-12)
    assert a.lr("positions", 400) == pytest.approx(ref.lr("positions", 400), rel=1e-12)
    rates = [a.lr("positions", t) for t in range(0, 2100, 50)]
    assert all(x >= y for x, y in zip(rates, rates[1:]))
    with pytest.raises(AdamError, match="steps must increase"):
        a.rehorizon(700, 3000)
    with pytest.raises(AdamError, match="0 < at < max_steps"):
        Adam(max_steps=100).rehorizon(100, 100)


def test_too_small_a_budget_names_the_option_and_the_smallest_that_works():
    costs = ProbeCosts(step=0.1, evaluation=0.2, rebuild=0.0, n=100, cap=100)

    def price(i):
        return loop_seconds(i, _scaled(make_config("r2"), i), i, costs)
    with pytest.raises(TimeBudgetError, match=r"time_budget=3 s is too small") as e:
        make_plan(3.0, 1.0, costs, price)
    smallest = float(str(e.value).rsplit("about ", 1)[1].split(" s")[0])
    plan = make_plan(smallest, 1.0, costs, price)           # that budget does work
    assert plan["iterations"] >= MIN_ITERATIONS
    assert plan["estimated_loop_seconds"] <= plan["loop_budget_seconds"]
    assert plan["loop_budget_seconds"] == pytest.approx(smallest * (1 - budget.RESERVE) - 1.0,
                                                        abs=1e-3)


def test_config_errors_name_time_budget():
    for bad in (0, -5):
        with pytest.raises(ConfigError, match=r"time_budget must be > 0 seconds"):
            make_config("gr", time_budget=bad)
    with pytest.raises(ConfigError, match=r"time_budget \(60 s\) plans the iteration count; "
                                          r"iterations=100"):
        make_config("gr", time_budget=60, iterations=100)
    assert make_config("gr", time_budget="none").run.time_budget is None
    assert make_config("gr", time_budget="90").run.time_budget == 90.0


def test_time_budget_in_an_xml_config(tmp_path):
    p = tmp_path / "c.xml"
    p.write_text('<training method="r2"><float name="time_budget" value="120"/></training>')
    assert read_config_xml(p) == ("r2", {"time_budget": 120.0})
    assert make_config("r2", p).run.time_budget == 120.0
    p.write_text('<training><float name="time_budget" value="none"/></training>')
    assert make_config("r2", p).run.time_budget is None


# ---------------------------------------------------------------------------- in training

def test_a_budget_run_is_the_planned_run(tiny_case, monkeypatch):
    """The probe draws no view of the run and leaves no optimiser or densifier state: the
    run after planning I iterations starts as the run with iterations=I does (same state,
    RNG, schedule) and takes the same steps up to the first densification (after it, float
    atomics in the backward pass may flip a densification decision in either run)."""
    monkeypatch.setattr(budget, "plan_iterations", lambda loop_budget, price: 120)
    monkeypatch.setattr(budget, "replan", lambda it, remaining, price_rest: 120)
    t = Trainer(tiny_case, make_config("gr", time_budget=600, **TINY), progress=False)
    ref = Trainer(tiny_case, make_config("gr", iterations=120, **TINY), progress=False)
    assert t.iterations == 120 and t.optimizer.max_steps == 120 and t.sched == ref.sched
    assert t.time_plan["iterations"] == 120 and t.time_plan["probe"]["step"] > 0
    assert t.rng.bit_generator.state == ref.rng.bit_generator.state
    assert t.optimizer.state == {} and t.densifier.state_dict()["grad_accum"] is None
    for k in t.state.raw:
        np.testing.assert_allclose(np.asarray(t.state.raw[k]), np.asarray(ref.state.raw[k]),
                                   atol=1e-6)
    info, ref_info = t.run(), ref.run()
    assert info["iterations_run"] == ref_info["iterations_run"] == 120
    assert info["time_plan"]["iterations"] == 120 and ref_info["time_plan"] is None
    first = min(it for it in range(1, 121) if t.densifier.is_densify_iteration(it))
    a = np.array([r["loss"] for r in t.state.log[:first]])
    b = np.array([r["loss"] for r in ref.state.log[:first]])
    np.testing.assert_allclose(a, b, rtol=1e-4)


def test_the_plan_moves_with_densification_then_is_replanned_once_more(tiny_case,
                                                                        monkeypatch):
    """Planned 120; every densification iteration re-plans (here to 130, 140, ...) and the
    window's end moves with the count (the scaled schedule's densify_stop of the new count);
    when the window closes, a final re-plan (here 400) sets the end: the run ends there with
    the learning rate decayed to its final ratio, and metrics record every re-plan."""
    monkeypatch.setattr(budget, "plan_iterations", lambda loop_budget, price: 120)
    asked = []

    def fake_replan(it, remaining, price_rest):
        asked.append((it, remaining, price_rest(it + 1), price_rest(it + 100)))
        return 400 if len(asked) > 1 and it == t.sched["densify_stop"] else 120 + 10 * len(asked)
    monkeypatch.setattr(budget, "replan", fake_replan)
    t = Trainer(tiny_case, make_config("r2", time_budget=600, **TINY), progress=False)
    start, interval = t.sched["densify_start"], t.sched["densify_interval"]
    info = t.run()
    replans = info["time_plan"]["replans"]
    assert [r["at"] for r in replans] == [a[0] for a in asked]
    window, final = replans[:-1], replans[-1]
    assert len(window) >= 2 and all(not r["final"] for r in window)
    for r in window:          # each window re-plan: the densification iterations, stop moved
        assert r["at"] % interval == 0 and r["at"] > start
        assert r["densify_stop"] == max(r["at"] + 1, _scaled(t.cfg, r["iterations"])["densify_stop"])
    assert final["final"] and final["at"] == window[-1]["densify_stop"] and final["iterations"] == 400
    assert final["densify_stop"] is None and final["growth_per_iteration"] == 0
    for it, remaining, one, hundred in asked:
        assert 0 < remaining < 600 and 0 < one < hundred
    assert info["iterations_run"] == 400 and info["iterations_planned"] == 400
    assert t.densifier.window.stop == final["at"]
    assert t.optimizer.lr("positions", 400) == pytest.approx(0.1 * t.optimizer.lr0["positions"])
    assert t.views.iterations == 400 and replans_done(info["time_plan"])


def test_the_loop_stops_at_its_share_of_the_budget(tiny_case, monkeypatch):
    """A plan that overestimates the machine: the loop's wall clock ends the run."""
    real = budget.make_plan

    def optimistic(b, setup, costs, price):
        plan = real(b, setup, costs, price)
        return {**plan, "iterations": 100000, "loop_budget_seconds": 1.0}
    monkeypatch.setattr(budget, "make_plan", optimistic)
    monkeypatch.setattr(budget, "replan", lambda it, remaining, price_rest: 100000)
    t = Trainer(tiny_case, make_config("r2", time_budget=600, **TINY), progress=False)
    info = t.run()
    assert info["stopped_by"].startswith("time budget (600 s) reached at iteration ")
    assert info["iterations_run"] < 100000 and info["train_seconds"] >= 1.0
    assert info["train_seconds"] < 1.0 + 10 * max(r["seconds"] for r in t.state.log[:1])


def test_a_resumed_budget_run_keeps_its_plan(tiny_case, tmp_path, monkeypatch, crash_after):
    """Planned 90, re-planned to 110 at every densification iteration (the window then ends
    at 55) and once more at 55, checkpointed at 60, crashed at 70: the resumed run replays
    the recorded plan (a machine of another speed would plan otherwise) and ends at 110."""
    monkeypatch.setattr(budget, "plan_iterations", lambda loop_budget, price: 90)
    monkeypatch.setattr(budget, "replan", lambda it, remaining, price_rest: 110)
    cfg = make_config("gr", time_budget=600, **{**TINY, "checkpoint_every": 30})
    crash_after(Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False), 70)
    monkeypatch.setattr(budget, "plan_iterations", lambda loop_budget, price: 500)
    monkeypatch.setattr(budget, "replan", lambda it, remaining, price_rest: 700)
    t = Trainer(tiny_case, cfg, out_dir=tmp_path, progress=False, resume=True)
    assert t.state.iteration == 60 and t.iterations == 110
    assert t.densifier.window.stop == 55 and t.optimizer.knots[-1][0] == 55
    assert t.optimizer.max_steps == 110 and t.views.iterations == 110
    knots = list(t.optimizer.knots)
    info = t.run()
    assert info["iterations_run"] == 110
    assert info["time_plan"]["iterations"] == 90
    final = info["time_plan"]["replans"][-1]
    assert (final["at"], final["iterations"], final["final"]) == (55, 110, True)
    assert [r["at"] for r in info["time_plan"]["replans"]] == [k[0] for k in knots]


def test_a_budget_counts_the_3d_log_on_its_clock(tiny_case, monkeypatch):
    """A time budget is wall clock: the research log's 3-D PSNR (here made to take 1 s)
    counts in a budget run's loop clock and is priced by the probe; a run without a budget
    leaves it out of its clock (train_seconds)."""
    import time

    from mi_grg.evaluation import metrics
    real = metrics.psnr_3d

    def slow(*a, **k):
        time.sleep(1.0)
        return real(*a, **k)
    monkeypatch.setattr(metrics, "psnr_3d", slow)
    monkeypatch.setattr(budget, "plan_iterations", lambda loop_budget, price: 100)
    monkeypatch.setattr(budget, "replan", lambda it, remaining, price_rest: 100)
    cfg = dict(TINY, eval_every=500, log_3d_every=40)

    def steps_after_logs(t):
        log = t.state.log
        return [b["seconds"] - a["seconds"] for a, b in zip(log, log[1:]) if "psnr_3d" in a]
    t = Trainer(tiny_case, make_config("r2", time_budget=600, **cfg), progress=False)
    assert t.time_plan["probe"]["log_3d"] >= 1.0
    t.run()
    after = steps_after_logs(t)
    assert len(after) == 2 and min(after) >= 1.0          # logs at 40 and 80 (and 100)
    ref = Trainer(tiny_case, make_config("r2", iterations=100, **cfg), progress=False)
    ref.run()
    after = steps_after_logs(ref)
    assert len(after) == 2 and max(after) < 1.0


def test_a_budget_too_small_for_one_evaluation_is_a_clear_error(tiny_case):
    with pytest.raises(TimeBudgetError, match=r"time_budget=0.01 s is too small for this "
                                              r"case: .* the smallest budget that works"):
        Trainer(tiny_case, make_config("r2", time_budget=0.01, **TINY), progress=False)
