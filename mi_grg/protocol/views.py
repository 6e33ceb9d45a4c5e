"""Which training views decide and which ones train, at each iteration.

One training view in every ``holdout_every`` is held out (evenly spread:
``mi_grg.protocol.split.holdout_split``): their projection error is the early-stop
rule's signal (``mi_grg.protocol.early_stop``). With sparse views every view is also worth
training on (measured: docs/benchmarks.md, "Every view counts"), so the held-out views
join training once no decision needs them any more:

- the decision window runs up to ``window_end``, the last evaluation at or before
  ``holdout_until`` x the iteration budget. The stop rule judges (and picks the state to
  keep) only on evaluations inside it; the held-out views are never trained on before
  ``window_end``.
- window closed without a stop: every view trains from ``window_end + 1`` to the budget, and
  the run returns its last state.
- the rule stopped at iteration s, keeping the state of iteration k <= s: training goes on
  from the kept state on every view for ``after_stop(k)`` = k x (budget - window_end) /
  window_end iterations (the share of all-view training a run that reaches the window's end
  gets), numbered s + 1, s + 2, ...; the run returns its last state. The run ends by
  ``s + after_stop(k) <= budget``: the protocol never adds iterations.

Honesty: a view's error is never used for a decision once that view has been trained on
(``test_views.py`` checks this over random schedules), and the ground truth never decides.

``catch_up``: from the join on, the step draws its view with ``draw_weights`` instead of
uniformly: the held-out views more often, so that every view's expected number of training
draws is the same at the run's end (as far as the remaining iterations allow: if they are
too few, only the held-out views train until the end). Off by default; a candidate protocol
(docs/benchmarks.md, "Every view counts").

``horizon``: a run longer than its schedule (``Schedule.horizon`` of the training config)
measures the window and the all-view share after a stop against the horizon instead of its
budget, so that it decides and stops exactly as the horizon-long run would; the iterations
past that run's end train every view.

``holdout_until = 1`` is the behaviour from before: held out for the whole run, the kept
state returned. Functions of the run's settings and of the stop (``Stop``) only, so that a
resumed run rebuilds the same protocol from its checkpointed stopper state.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from mi_grg.protocol.split import decision_split, holdout_split


class Stop(NamedTuple):
    """Where the stop rule fired (``iteration``) and the state it kept (``kept_iteration``)."""
    iteration: int
    kept_iteration: int


def stop_from(stopper_state: dict | None) -> Stop | None:
    """The ``Stop`` recorded in an ``EarlyStopper.state_dict()``; None if it never fired."""
    if not stopper_state or stopper_state.get("reason") is None:
        return None
    return Stop(int(stopper_state["history"][-1][0]), int(stopper_state["kept_iteration"]))


@dataclass(frozen=True)
class ViewProtocol:
    """The view schedule of one run (see the module docstring).

    n_views: training views; holdout_every: hold out views 0, n, 2n, ... (0: none);
    holdout_until: fraction of ``iterations`` during which they stay held out, in [0, 1];
    iterations: the run's budget; eval_every: interval between held-out evaluations;
    catch_up: after the join, draw the held-out views more often (``draw_weights``);
    horizon: the schedule's length when the run is longer (``Schedule.horizon``): the
    window and the all-view share after a stop are measured against it, the iterations
    past it train every view (None: the run's budget)."""

    n_views: int
    holdout_every: int
    holdout_until: float
    iterations: int
    eval_every: int
    catch_up: bool = False
    horizon: int | None = None

    def __post_init__(self):
        if not 0.0 <= self.holdout_until <= 1.0:
            raise ValueError(f"holdout_until must be a fraction in [0, 1], got "
                             f"{self.holdout_until}")
        if self.n_views < 1 or self.iterations < 1 or self.eval_every < 1:
            raise ValueError("n_views, iterations and eval_every must be >= 1")
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"horizon must be >= 1 or None, got {self.horizon}")
        if self.holdout_every:
            decision_split(self.n_views, self.holdout_every, "the stop rule")

    # ------------------------------------------------------------------ the view sets
    @cached_property       # asked at every iteration; the settings are frozen
    def held(self) -> np.ndarray:
        """Views held out for decisions, [k] int (``mi_grg.protocol.split.holdout_split``)."""
        return holdout_split(self.n_views, self.holdout_every)[1]

    @cached_property
    def fit(self) -> np.ndarray:
        """Views trained while the held-out ones decide, [n_views - k] int."""
        return holdout_split(self.n_views, self.holdout_every)[0]

    @property
    def scheduled(self) -> int:
        """The iterations the window is measured against: the budget, or the horizon when
        the budget is longer."""
        return self.iterations if self.horizon is None else min(self.iterations, self.horizon)

    @property
    def window_end(self) -> int:
        """Last iteration whose evaluation may decide (0: none can)."""
        if len(self.held) == 0:
            return 0
        if self.holdout_until >= 1.0:
            return self.iterations
        # a small tolerance so that 0.75 x 1500 is 1125, not 1124.999...
        limit = int(self.holdout_until * self.scheduled + 1e-9)
        return limit // self.eval_every * self.eval_every

    def after_stop(self, kept_iteration: int) -> int:
        """Iterations on every view after the stop rule fired, keeping ``kept_iteration``."""
        w = self.window_end
        if w == 0 or w >= self.scheduled:
            return 0
        return int(round(kept_iteration * (self.scheduled - w) / w))

    # ------------------------------------------------------------------ per iteration
    def joined(self, iteration: int, stop: Stop | None = None) -> bool:
        """Whether the held-out views have joined training by the step of ``iteration``
        (False when none are held out)."""
        if len(self.held) == 0:
            return False
        if stop is not None:
            return self.after_stop(stop.kept_iteration) > 0 and iteration > stop.iteration
        return iteration > self.window_end

    def train_views(self, iteration: int, stop: Stop | None = None) -> np.ndarray:
        """Views the training step of ``iteration`` draws from."""
        if self.joined(iteration, stop):
            return np.arange(self.n_views, dtype=np.int64)
        return self.fit

    def draw_weights(self, iteration: int, stop: Stop | None = None) -> np.ndarray | None:
        """Probabilities over ``train_views(iteration, stop)``, [len] float64, or None for a
        uniform draw (before the join, or without ``catch_up``).

        Before the join each fit view was drawn (kept state's iteration) / |fit| times on
        average and each held-out view never; over the R iterations from the join to
        ``end(stop)``, p_fit = (1 - k a / R) / n and p_held = p_fit + a / R (a: the fit
        views' expected draws, k held-out of n views) make the expected totals equal; when
        k a > R, p_fit = 0 and the held-out views share every draw."""
        if not (self.catch_up and self.joined(iteration, stop)):
            return None
        join, kept = self._join(stop)
        remaining = self.end(stop) - join + 1
        n, k = self.n_views, len(self.held)
        a = kept / (n - k)
        p_fit = max(0.0, 1.0 - k * a / remaining) / n
        w = np.full(n, p_fit)
        w[self.held] = (1.0 - (n - k) * p_fit) / k
        return w

    def _join(self, stop: Stop | None) -> tuple[int, int]:
        """(first iteration on every view, iteration of the state it starts from), given
        that the held-out views join: after the stop's iteration from its kept state, else
        after the window's end."""
        if stop is not None:
            return stop.iteration + 1, stop.kept_iteration
        return self.window_end + 1, self.window_end

    def decides(self, iteration: int, stop: Stop | None = None) -> bool:
        """Whether the held-out evaluation after the step of ``iteration`` may be made and
        judged (no held-out view trained yet, the rule not yet fired)."""
        return len(self.held) > 0 and stop is None and iteration <= self.window_end

    def end(self, stop: Stop | None = None) -> int:
        """The run's last iteration."""
        if stop is None:
            return self.iterations
        return stop.iteration + self.after_stop(stop.kept_iteration)

    # ------------------------------------------------------------------ the record
    def record(self, iteration: int, stop: Stop | None, decisions: list,
               reason: str | None = None, returned_iteration: int | None = None) -> dict:
        """What decided what, for metrics.json: ``iteration`` is the last one run,
        ``decisions`` the stop rule's judged (iteration, held-out value) pairs,
        ``returned_iteration`` the iteration whose state the run returns."""
        held = self.held.tolist()
        joined = self.joined(iteration, stop)
        join_at = self._join(stop)[0] if joined else None
        trained = list(range(self.n_views)) if joined else self.fit.tolist()
        return {
            "holdout_until": self.holdout_until,
            "catch_up": self.catch_up,
            "held_out_views": held,
            "decision_window_end": self.window_end if held else 0,
            # the stop rule's evaluations: each on the held-out views, none of them trained
            "decisions": [{"iteration": int(i), "heldout_psnr": float(v),
                           "views": held} for i, v in decisions],
            "stop": None if stop is None else {"iteration": stop.iteration,
                                               "kept_iteration": stop.kept_iteration,
                                               "reason": reason},
            "held_out_views_trained_from": join_at,
            "iterations_on_all_views": (iteration - join_at + 1 if join_at
                                        else 0 if held else iteration),
            "returned_state_iteration": returned_iteration,
            "trained_on_views": trained,
        }
