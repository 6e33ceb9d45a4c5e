"""A ``time_budget`` run's planning, applied to its trainer: the plan from a probe of this
machine's speed (or a resumed run's recorded plan, replayed), the replans on the way, and
the end of the run moved with them. The planner itself (what to plan) is
``mi_grg.training.budget``; this holds what the trainer does with its answers."""
from __future__ import annotations

import dataclasses
import time

import drjit as dr
import numpy as np

from mi_grg.training.budget import BudgetPlanner, replans_of
from mi_grg.training.schedule import _scaled, gaussian_cap


def second_of_two(fn) -> float:
    """Seconds of the second of two calls of ``fn`` (the first traces and compiles)."""
    fn()
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


class TimeBudget:
    """The time budget of ``trainer`` (its ``cfg.run.time_budget``)."""

    def __init__(self, trainer):
        self.trainer = t = trainer

        def window_end(iterations: int, eval_every: int) -> int:
            return dataclasses.replace(t.views, iterations=iterations,
                                       eval_every=eval_every).window_end
        self.planner = BudgetPlanner(t.cfg.run.time_budget, gaussian_cap(t.cfg, t.case.geometry),
                                     lambda iterations: _scaled(t.cfg, t._scheduled(iterations)),
                                     window_end, self.logs_3d, plan=t.state.time_plan)

    def start(self, resuming: bool, g, t_begin: float) -> None:
        """Plan the run from a probe on ``g`` (the first Gaussians); a resumed run replays
        its recorded plan instead (another machine would plan otherwise)."""
        t = self.trainer
        if resuming:
            for r in replans_of(self.planner.plan):
                self.set_rest_of_run(r["at"], r["iterations"], r.get("densify_stop"))
            return
        t.state.time_plan = self.planner.plan_run(len(g), lambda: self.probe(g), t_begin)
        t._schedule(t.time_plan["iterations"])

    def after_iteration(self, it: int, densified: bool, seconds: float, n: int) -> bool:
        """Replan at ``it`` when the planner wants to; True when it did."""
        t = self.trainer
        if not self.planner.wants_replan(it, densified, t.sched["densify_stop"]):
            return False
        r = self.planner.replan(it, seconds, n, t.state.log, t.sched,
                                t.densifier.is_densify_iteration)
        if r is not None:
            self.set_rest_of_run(it, r["iterations"], r["densify_stop"])
        return True

    def out_of_time(self, seconds: float) -> bool:
        return self.planner.out_of_time(seconds)

    def set_rest_of_run(self, at: int, iterations: int, densify_stop: int | None = None) -> None:
        """The run ends at ``iterations`` instead (decided at iteration ``at``): the held-out
        window moves with it, the learning-rate decay is stretched to it without a jump, and
        (while densifying) the window ends at ``densify_stop``. The densification and
        evaluation intervals stay as first planned."""
        t = self.trainer
        t.iterations = int(iterations)
        t.views = dataclasses.replace(t.views, iterations=t.iterations)
        end = t._scheduled(t.iterations)
        if at < min(end, t.optimizer.max_steps):   # else the decay is past its end
            t.optimizer.rehorizon(at, end)
        if densify_stop is not None:
            t.sched["densify_stop"] = int(densify_stop)
            t.densifier.window = dataclasses.replace(t.densifier.window, stop=int(densify_stop))

    def probe(self, g, steps: int = 8) -> dict:
        """Seconds of one training iteration (mean of ``steps`` after two warm-up ones that
        compile the kernels), one held-out evaluation, one graph rebuild and one 3-D PSNR
        log (each the second of two), on a copy of ``g`` with the current (provisional)
        optimiser and densifier, which ``_schedule`` replaces afterwards; the run's RNG is
        not drawn."""
        t = self.trainer
        raw = g.to_raw()
        for v in raw.values():
            dr.enable_grad(v)
        rng, t.rng = t.rng, np.random.default_rng(0)
        rebuild = 0.0
        try:
            if t.uses_graph:
                rebuild = second_of_two(lambda: t._rebuild_graph(raw["positions"]))
            for it in (1, 2):
                raw, _ = t._step(it, raw)
            t0 = time.perf_counter()
            for it in range(3, 3 + steps):
                raw, _ = t._step(it, raw)
            step = (time.perf_counter() - t0) / steps
            evaluation = log_3d = 0.0
            if len(t.held_idx):
                evaluation = second_of_two(lambda: t._heldout_psnr(raw))
            if t.case.vol_gt is not None:
                log_3d = second_of_two(lambda: t._psnr_3d(raw))
        finally:
            t.rng, t.graph, t._density_scale = rng, None, None
        return {"step": step, "evaluation": evaluation, "rebuild": rebuild, "log_3d": log_3d}

    def logs_3d(self, iterations: int, after: int, eval_every: int) -> int:
        """How many 3-D PSNR logs (``Trainer._evaluate``) iterations after+1 ..
        ``iterations`` make: one every ``log_3d_every`` (else at every evaluation), one
        at the end."""
        t = self.trainer
        if t.case.vol_gt is None:
            return 0
        every = t.cfg.protocol.log_3d_every or eval_every
        return max(0, iterations // every - after // every) + 1
