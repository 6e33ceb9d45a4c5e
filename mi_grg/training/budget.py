"""A training run planned to a wall-clock budget (``Run.time_budget`` of ``TrainConfig``).

With ``time_budget = SECONDS`` the trainer does not take its iteration count from
``trainer.iteration_rule`` but plans it, after De-Init, from what this machine measures:

1. a probe times a few training iterations on the initial Gaussians (after two warm-up
   iterations that trace and compile the kernels), one held-out evaluation and one graph
   rebuild, on throw-away copies of the state (the run itself starts afterwards from the
   untouched initial state, with a fresh optimiser and densifier);
2. ``loop_seconds`` prices a schedule of I iterations with that probe: iterations before
   densification starts cost the probe's step; from then on every iteration, densification
   + graph rebuild and held-out evaluation is priced at the densification cap, scaling the
   probe's cost linearly with the Gaussian count. That overestimates (densification reaches
   the cap only gradually, and split Gaussians are smaller, so each costs less), so a plan
   ends early rather than late;
3. ``plan_iterations`` takes the largest I whose price fits the loop's share of the budget
   (the budget minus the time already spent on De-Init and the probe, minus ``RESERVE`` of
   the budget for writing the result); the schedule (densification window, learning-rate
   decay, evaluation interval, held-out window) scales with I as it does with the rule's,
   up to the horizon (``Schedule.horizon``; a longer plan anneals past it);
4. the plan is then corrected from the loop's own clock (``rest_seconds``): at every
   densification iteration the rest of the run is re-priced from the measured seconds per
   iteration and Gaussian and the count's recent growth, extrapolated linearly (up to the
   cap) to the end of the window, which moves with the new count (the scaled schedule's
   densify_stop); when densification ends the count is final and the rest is re-planned
   once more at the measured pace. Without these corrections a large grid, whose count
   stays far below the cap (256^3: about 85k of 500k), would be planned several times
   too short. Every re-plan stretches or shrinks the learning-rate decay to the new end
   without a jump (``Adam.rehorizon``) and moves the held-out window with it; the
   densification and evaluation intervals stay as first planned;
5. the loop also stops when its wall clock reaches its share, whatever the plan said
   ("time budget ... reached"), so the budget holds on a machine that slows down mid-run.

The budget covers the trainer, from De-Init to the returned state's files, on the wall
clock: in a time_budget run the research log's 3-D PSNR (when the case has a ground truth)
counts and is priced (at 256^3 one is a sizeable part of the loop; elsewhere the trainer
leaves it out of ``train_seconds``); the volume and scores that ``mi_grg.reconstruct`` computes
afterwards are not part of it (``RESERVE`` leaves room for them).
metrics.json ``method_info.time_plan`` records the probe, the plan and the loop's share.
``BudgetPlanner`` holds one run's plan; the trainer asks it and applies its answers.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np

from mi_grg.training.densify import densify_iterations

#: Fewest iterations a budget must allow: one evaluation interval (the smallest
#: ``eval_every`` of a scaled schedule), so that the run is evaluated at least once.
MIN_ITERATIONS = 50
#: Share of the budget kept back for what follows the loop (final checkpoint, files).
RESERVE = 0.05
#: Share of the loop's remaining time that the re-plan spends (the pace varies a little).
REPLAN_SHARE = 0.97


class TimeBudgetError(ValueError):
    """A budget that cannot be planned; the message names ``time_budget``."""


@dataclass(frozen=True)
class ProbeCosts:
    """Seconds measured by the probe on ``n`` Gaussians; ``cap``: the densification cap.

    step: one training iteration (its TV share included); evaluation: one held-out
    evaluation (0 without held-out views); rebuild: one graph rebuild (0 without a graph);
    log_3d: one 3-D PSNR of the research log (volume + score; 0 without a ground truth)."""
    step: float
    evaluation: float
    rebuild: float
    n: int
    cap: int
    log_3d: float = 0.0

    def __post_init__(self):
        for name in ("step", "evaluation", "rebuild", "log_3d"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"probe {name} seconds must be finite and >= 0, got {v}")
        if self.n < 1 or self.cap < 1:
            raise ValueError(f"n and cap must be >= 1, got {self.n}, {self.cap}")

    @property
    def growth(self) -> float:
        """Cost factor at the cap against the probe (linear in the count, never below 1)."""
        return max(1.0, self.cap / self.n)


def loop_seconds(iterations: int, schedule: dict, window_end: int, costs: ProbeCosts,
                 logs_3d: int = 0) -> float:
    """Price of a training loop of ``iterations`` with the scaled ``schedule``
    (densify_start / densify_stop / densify_interval / eval_every, as ``trainer._scaled``
    returns), held-out evaluations up to ``window_end`` (and one at the end) and
    ``logs_3d`` 3-D PSNR logs."""
    start = min(schedule["densify_start"], iterations)
    densify = len(densify_iterations(schedule["densify_start"], schedule["densify_stop"],
                                     schedule["densify_interval"], iterations))
    evaluations = window_end // schedule["eval_every"] + 1
    g = costs.growth
    return (start * costs.step + (iterations - start) * g * costs.step
            + densify * g * costs.rebuild + evaluations * g * costs.evaluation
            + logs_3d * g * costs.log_3d)


def plan_iterations(loop_budget: float, price) -> int | None:
    """The largest iteration count I >= ``MIN_ITERATIONS`` with ``price(I) <= loop_budget``
    (``price``: seconds for I iterations, non-decreasing in I); None if not even
    ``MIN_ITERATIONS`` fit."""
    if price(MIN_ITERATIONS) > loop_budget:
        return None
    return _largest(MIN_ITERATIONS, lambda i: price(i) <= loop_budget)


def _largest(first: int, fits) -> int:
    """The largest n >= ``first`` with ``fits(n)``, for ``fits`` true at ``first`` and, as n
    grows, true up to some n and false after it: steps doubling, then bisection."""
    lo, step = first, 1
    while fits(lo + step):
        lo, step = lo + step, 2 * step
        if step > 10**8:
            raise TimeBudgetError("time_budget: over 10^8 iterations fit; the probe measured "
                                  "no cost")
    hi = lo + step                        # fits(lo), not fits(hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def make_plan(budget: float, setup_seconds: float, costs: ProbeCosts, price) -> dict:
    """The plan of a run with ``time_budget = budget`` after ``setup_seconds`` of De-Init and
    probe: {"iterations", "loop_budget_seconds", ...} for metrics.json. Raises
    ``TimeBudgetError`` (naming time_budget and the smallest budget that works) when not even
    one evaluation interval fits."""
    loop_budget = budget * (1.0 - RESERVE) - setup_seconds
    iterations = plan_iterations(loop_budget, price)
    if iterations is None:
        need = (setup_seconds + price(MIN_ITERATIONS)) / (1.0 - RESERVE)
        raise TimeBudgetError(
            f"time_budget={budget:g} s is too small for this case: De-Init and the probe took "
            f"{setup_seconds:.1f} s, and one evaluation interval ({MIN_ITERATIONS} "
            f"iterations) needs about {price(MIN_ITERATIONS):.1f} s more; the smallest budget "
            f"that works here is about {math.ceil(need)} s")
    return {"time_budget_seconds": float(budget), "setup_seconds": round(setup_seconds, 3),
            "loop_budget_seconds": round(loop_budget, 3), "iterations": int(iterations),
            "estimated_loop_seconds": round(price(iterations), 3),
            "probe": {k: (round(v, 5) if isinstance(v, float) else v)
                      for k, v in asdict(costs).items()}}


def measured_pace(seconds: list, priced_apart=None) -> float:
    """Seconds per iteration from the loop's cumulative clock at consecutive iterations:
    the mean step, leaving out the steps marked in ``priced_apart`` (one flag per step:
    it carried an evaluation, a 3-D log or a densification and graph rebuild, which the
    plan prices on their own). Every other step counts, however long: the TV term's
    every-other-iteration cost and, on a GPU, kernels that finish in a later step's host
    sync belong to the pace. (A filter by size such as "over 3x the median" cannot tell
    those from spikes: where a TV step costs over 3x a plain one, as on a GPU whose plain
    step is a few ms, it priced the loop at its plain steps alone.)"""
    steps = [b - a for a, b in zip(seconds, seconds[1:])]
    if not steps:
        raise ValueError("need the clock at two iterations at least")
    skip = list(priced_apart) if priced_apart is not None else [False] * len(steps)
    if len(skip) != len(steps):
        raise ValueError(f"priced_apart has {len(skip)} flags for {len(steps)} steps")
    kept = [d for d, s in zip(steps, skip) if not s] or steps
    return sum(kept) / len(kept)


def replan(iteration: int, remaining_seconds: float, price_rest) -> int:
    """The iteration count for the rest of a run at ``iteration`` with
    ``remaining_seconds`` of its loop's share left: the largest I > iteration with
    ``price_rest(I) <= REPLAN_SHARE x remaining_seconds`` (``price_rest``: seconds of the
    iterations iteration+1..I and their evaluations), at least iteration + 1."""
    room = REPLAN_SHARE * remaining_seconds
    if price_rest(iteration + 1) > room:
        return iteration + 1
    return _largest(iteration + 1, lambda i: price_rest(i) <= room)


@dataclass(frozen=True)
class LoopPace:
    """What the loop measured when a re-plan is made at iteration ``at``.

    per_gaussian: seconds per iteration and Gaussian (the recent mean step over the recent
    mean count: a step is priced linearly in the count, which over-estimates, as
    ``loop_seconds`` does); n: the count now; growth: Gaussians added per iteration
    recently (0 once densification is over); cap: the densification cap;
    rebuild / evaluation / log_3d: seconds per Gaussian of one densification + graph
    rebuild (as measured on the loop's densification iterations), of one held-out
    evaluation and of one 3-D PSNR log (the probe's, scaled from its count)."""
    at: int
    per_gaussian: float
    n: int
    growth: float
    cap: int
    rebuild: float
    evaluation: float
    log_3d: float = 0.0


def rest_seconds(pace: LoopPace, iterations: int, densify_stop: int, densify: range,
                 evaluations: int, logs_3d: int = 0) -> float:
    """Price of iterations ``pace.at`` + 1 .. ``iterations`` when densification goes on
    until ``densify_stop`` (exclusive) at the densification iterations ``densify`` and
    ``evaluations`` held-out evaluations and ``logs_3d`` 3-D PSNR logs remain: the count
    grows linearly at the recent rate, up to the cap, while the window is open
    (densification slows down as it goes, so this over-estimates) and stays where it got
    to after it; each evaluation and log is priced at the final count."""
    if iterations <= pace.at:
        return 0.0

    def count(t):
        grown = pace.growth * (np.minimum(t, densify_stop) - pace.at)
        return np.minimum(float(pace.cap), pace.n + np.maximum(grown, 0.0))
    steps = count(np.arange(pace.at + 1, iterations + 1, dtype=np.float64))
    events = np.asarray([t for t in densify if t > pace.at], np.float64)
    return float(pace.per_gaussian * steps.sum() + pace.rebuild * count(events).sum()
                 + (pace.evaluation * evaluations + pace.log_3d * logs_3d)
                 * count(float(iterations)))


def replans_of(plan: dict | None) -> list:
    """The re-plans recorded in a time plan, in order (a plan written before the re-plans
    moved with densification kept only the final one, as ``replanned``)."""
    if not plan:
        return []
    if "replanned" in plan:
        return [dict(plan["replanned"], final=True)]
    return list(plan.get("replans", []))


def replans_done(plan: dict) -> bool:
    """Whether the final re-plan (made when densification ended) has been made."""
    return any(r.get("final") for r in replans_of(plan))


class BudgetPlanner:
    """The time plan of one ``time_budget`` run; the trainer asks it, and applies what it says.

    ``plan_run`` prices the run's schedule from the probe and fixes the iteration count;
    ``wants_replan`` / ``replan`` re-price the rest from the loop's own clock; ``out_of_time``
    is the deadline. The plan itself is a dict (metrics.json's ``time_plan``) that the
    trainer keeps in its state, so that checkpoints carry it and a resumed run replays its
    re-plans (``replans_of``).

    What depends on the run comes in as functions of an iteration count I:
    ``scaled(I)``: the scaled schedule (densify_start / densify_stop / densify_interval /
    eval_every); ``window_end(I, eval_every)``: the end of the held-out window;
    ``logs_3d(I, after, eval_every)``: the 3-D PSNR logs of iterations after+1 .. I."""

    def __init__(self, budget: float, cap: int, scaled, window_end, logs_3d, plan=None):
        self.budget, self.cap = float(budget), int(cap)
        self.scaled, self.window_end, self.logs_3d = scaled, window_end, logs_3d
        self.plan = plan

    def plan_run(self, n: int, probe, t_begin: float) -> dict:
        """Probe (``probe()``: ProbeCosts' seconds on the ``n`` initial Gaussians), then the
        plan of the whole run; the time since ``t_begin`` (De-Init and probe) counts."""
        costs = ProbeCosts(**probe(), n=n, cap=self.cap)

        def price(iterations: int) -> float:
            s = self.scaled(iterations)
            return loop_seconds(iterations, s, self.window_end(iterations, s["eval_every"]),
                                costs, self.logs_3d(iterations, 0, s["eval_every"]))
        self.plan = make_plan(self.budget, time.perf_counter() - t_begin, costs, price)
        return self.plan

    def wants_replan(self, it: int, densified: bool, densify_stop: int) -> bool:
        """Re-plan at every densification iteration and once when the window closes."""
        return not replans_done(self.plan) and (densified or it == densify_stop)

    def out_of_time(self, loop_seconds_so_far: float) -> bool:
        """Whether the loop's wall clock has reached its share of the budget."""
        return loop_seconds_so_far >= self.plan["loop_budget_seconds"]

    def replan(self, it: int, seconds: float, n: int, log: list, sched: dict,
               is_densify_iteration) -> dict | None:
        """The rest of the run re-planned at iteration ``it`` (loop clock ``seconds``, ``n``
        Gaussians) from the loop's ``log`` rows: while densifying, the count's recent growth
        priced up to the end of the window, which moves with the new count; when
        densification ends (N final), once more at the measured pace. Returns the re-plan
        {"at", "iterations", "densify_stop" (None once final), ...}, also recorded in the
        plan's ``replans``; None without log rows."""
        rows = log[-max(1, min(200, it // 4)):]   # the last quarter, <= 200 iterations
        if not rows:
            return None
        final = it >= sched["densify_stop"]
        pace, step = self._pace(it, seconds, n, rows, final, is_densify_iteration)
        every = sched["eval_every"]

        def stop_for(iterations: int) -> int:
            return sched["densify_stop"] if final else \
                max(it + 1, self.scaled(iterations)["densify_stop"])

        def price_rest(iterations: int) -> float:
            stop = stop_for(iterations)
            evals = max(0, self.window_end(iterations, every) // every - it // every) + 1
            events = densify_iterations(sched["densify_start"], stop, sched["densify_interval"],
                                        iterations)
            return rest_seconds(pace, iterations, stop, events, evals,
                                self.logs_3d(iterations, it, every))
        iterations = replan(it, self.plan["loop_budget_seconds"] - seconds, price_rest)
        record = {"at": it, "iterations": iterations,
                  "densify_stop": None if final else stop_for(iterations), "final": final,
                  "n": n, "seconds_per_iteration": round(step, 5),
                  "growth_per_iteration": round(pace.growth, 2)}
        self.plan.setdefault("replans", []).append(record)
        return record

    def _pace(self, it, seconds, n, rows, final, is_densify_iteration):
        """(LoopPace, seconds per plain step) measured on the log ``rows`` up to ``it``."""
        counts = [r["n_gaussians"] for r in rows]
        clock = [r["seconds"] for r in rows] + [seconds]
        # Step k runs iteration rows[k] + 1 on rows[k]'s count, after rows[k]'s evaluation
        # and 3-D log (if any); both and densification are priced apart.
        evaluated = ["heldout_psnr" in r or "psnr_3d" in r for r in rows]
        densifying = [is_densify_iteration(r["iteration"] + 1) for r in rows]
        step = measured_pace(clock, [e or d for e, d in zip(evaluated, densifying)])
        growth = 0.0 if final else max(0.0, (n - counts[0]) / max(1, it - rows[0]["iteration"]))
        probe = self.plan["probe"]
        # A densification iteration's extra time, measured (the probe times only the graph
        # rebuild): its step beyond the pace, per Gaussian.
        extra = [(clock[k + 1] - clock[k] - step) / prev["n_gaussians"]
                 for k, prev in enumerate(rows) if densifying[k] and not evaluated[k]]
        rebuild = max(probe["rebuild"] / probe["n"], sum(extra) / len(extra) if extra else 0.0)
        pace = LoopPace(at=it, per_gaussian=step / (sum(counts) / len(counts)), n=n,
                        growth=growth, cap=probe["cap"], rebuild=rebuild,
                        evaluation=probe["evaluation"] / probe["n"],
                        log_3d=probe.get("log_3d", 0.0) / probe["n"])
        return pace, step
