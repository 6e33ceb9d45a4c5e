"""Early stopping without ground truth: watch the PSNR of held-out training views.

The paper evaluates PSNR every 500 iterations and stops "if the PSNR decreases by more than
0.5 %". We compare with the BEST value so far (not only the previous one), so a slow slide
of several small drops also stops the run; the caller keeps a state (see below).

``patience`` is the number of evaluations in a row that must lie below that margin
(1 = the paper's rule as written). At our scaled schedules (an evaluation every 125
iterations up to 7500 iterations, e.g. 24 in a 64^3 run's 3000, rather than 60 in 30k)
the held-out PSNR still rises late in training and
wobbles around that trend by about the margin itself, so a single dip ended runs that
recovered at the next evaluation (docs/benchmarks.md, "Measurements behind defaults").
The default is 2 (``STOP_RULE``).

Which state to keep (``Protocol.keep_state`` of ``TrainConfig``): the same wobble makes "the state with the
highest held-out PSNR" an early state by chance, with a worse 3-D PSNR than a later state
within the margin (docs/benchmarks.md, "Reconstruction"). "latest" (the default) therefore
keeps the LATEST state whose value lies within the stop rule's margin of the best (its
noise margin: it does not call such a state worse); "best" keeps the literal maximum. ``EarlyStopper.kept_iteration`` names the state to hold.

The margin is also at least ``noise`` x sigma, sigma the held-out PSNR's own scatter from
one evaluation to the next (``scatter``: a robust estimate from the third differences of
every evaluation the stopper has seen, judged or not). Why: the best value is the maximum
of noisy evaluations, and the drop fraction alone is smaller than one sigma of the scatter
seen in real runs, so it stopped runs whose held-out and 3-D PSNR went on rising
(docs/benchmarks.md, "Are the 128^3 stops right?"). ``stop_noise`` is 3: on synthetic
curves it cuts the false stops of a noisy rising curve many fold and delays the stop of a
real decline by a few evaluations (bench/stop_rule.py, docs/bench/stop_rule.md). Why 3,
not 2: the third differences see only the fast part of the scatter, and SGD's is
correlated over evaluations (a run of similar views moves the state for a while), so a
dip of several estimated sigmas can still recover. 0 is the rule as it was.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field

#: Which state a run keeps (``Protocol.keep_state`` of ``TrainConfig``, ``EarlyStopper.keep``).
KEEP_STATES = ("latest", "best")


@dataclass(frozen=True)
class StopRule:
    """The stop rule's settings, shared by every method (gr / r2 take theirs from
    ``TrainConfig``, whose defaults are these): hold out one view in ``holdout_every``;
    stop when the held-out PSNR lies more than max(``drop`` x best, ``noise`` x its
    scatter) below its best at ``patience`` evaluations in a row; keep the ``keep``
    state."""

    holdout_every: int = 8
    drop: float = 0.005
    patience: int = 2
    noise: float = 3.0
    keep: str = "latest"

    def stopper(self, label: str = "held-out PSNR") -> "EarlyStopper":
        return EarlyStopper(drop=self.drop, patience=self.patience, noise=self.noise,
                            keep=self.keep, label=label)


#: The defaults (docstrings above and in TrainConfig say why each).
STOP_RULE = StopRule()


@dataclass
class EarlyStopper:
    """Stop when ``value < best - margin`` at ``patience`` evaluations in a row, where
    ``margin = max(drop * |best|, noise * scatter())``; ``drop`` is a fraction (0.005 =
    0.5 %), ``noise`` a multiple of the values' scatter (0: the fraction alone).

    ``update`` returns "improved" (a new best), "within" (below the best by at most the margin),
    "below" (further below, fewer than ``patience`` times in a row) or "stop"; ``reason`` says
    why the run stopped ("held-out PSNR fell ..."), ``best`` / ``best_iteration`` where it
    peaked. ``kept_iteration`` is the evaluation whose state the caller should hold: by
    ``keep``, the latest "improved" or "within" one ("latest") or the best ("best").
    """

    drop: float = 0.005
    patience: int = 1
    label: str = "held-out PSNR"
    best: float = -math.inf
    best_iteration: int = -1
    keep: str = "latest"
    kept_iteration: int = -1       # the evaluation whose state to keep (see ``keep``)
    history: list = field(default_factory=list)
    reason: str | None = None
    below: int = 0                 # evaluations in a row below the margin so far
    noise: float = 0.0             # the margin is at least noise x scatter()
    seen: list = field(default_factory=list)   # every (iteration, value), judged or not

    def __post_init__(self):
        if not 0 <= self.drop < 1:
            raise ValueError(f"drop must be a fraction in [0, 1), got {self.drop}")
        if int(self.patience) != self.patience or self.patience < 1:
            raise ValueError(f"patience must be an integer >= 1, got {self.patience}")
        if self.keep not in KEEP_STATES:
            raise ValueError(f"keep must be one of {', '.join(KEEP_STATES)}, got {self.keep!r}")
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise ValueError(f"noise must be a finite multiple >= 0 of the scatter, got "
                             f"{self.noise}")

    def observe(self, iteration: int, value: float) -> None:
        """An evaluation that is not judged (e.g. during densification): it only informs
        ``scatter``."""
        if math.isnan(value):
            raise FloatingPointError(f"{self.label} is NaN at iteration {iteration}")
        self.seen.append((int(iteration), float(value)))

    def scatter(self) -> float:
        """The values' scatter from one evaluation to the next (a standard deviation, in the
        values' unit): 1.4826 x the median |third difference| / sqrt(20), which is sigma for
        independent Gaussian scatter around a trend that is locally quadratic. Third, not
        second, differences so that a smooth curve's bend (a deterministic method's held-out
        curve has no scatter at all) does not pass for scatter; the median ignores the few
        places where the trend changes shape. 0 with fewer than 6 values seen."""
        v = [x for _, x in self.seen if math.isfinite(x)]
        d3 = [v[i + 3] - 3 * v[i + 2] + 3 * v[i + 1] - v[i] for i in range(len(v) - 3)]
        if len(d3) < 3:
            return 0.0
        return 1.4826 * statistics.median(abs(d) for d in d3) / math.sqrt(20)

    def margin(self) -> float:
        """How far below the best a value may lie and still count as level with it."""
        # PSNR can be negative in dB only for hopeless fits; use the magnitude.
        m = self.drop * abs(self.best)
        return max(m, self.noise * self.scatter()) if self.noise else m

    def update(self, iteration: int, value: float) -> str:
        if not math.isfinite(value):
            # An infinite PSNR means an exact fit (improvement); NaN is a failure.
            if math.isnan(value):
                raise FloatingPointError(f"{self.label} is NaN at iteration {iteration}")
        self.history.append((int(iteration), float(value)))
        self.seen.append((int(iteration), float(value)))
        if value > self.best:
            self.best, self.best_iteration = float(value), int(iteration)
            self.below, self.kept_iteration = 0, int(iteration)
            return "improved"
        margin = self.margin()
        if value >= self.best - margin:
            self.below = 0
            if self.keep == "latest":
                self.kept_iteration = int(iteration)
            return "within"
        self.below += 1
        if self.below < self.patience:
            return "below"
        row = (f" ({self.patience} evaluations in a row)" if self.patience > 1 else "")
        by = (f"{100 * self.drop:g} %" if margin <= self.drop * abs(self.best) else
              f"{margin:.3f} ({self.noise:g} x its scatter {self.scatter():.3f})")
        self.reason = (f"{self.label} fell from {self.best:.3f} (iteration "
                       f"{self.best_iteration}) to {value:.3f} at iteration {iteration}, "
                       f"a drop of more than {by}{row}")
        return "stop"

    def state_dict(self) -> dict:
        """The evaluation state (JSON-serialisable); the settings (drop, patience, keep,
        noise, label) are the constructor's."""
        return {"best": self.best, "best_iteration": self.best_iteration,
                "kept_iteration": self.kept_iteration,
                "history": list(self.history), "reason": self.reason, "below": self.below,
                "seen": list(self.seen)}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output."""
        self.best, self.best_iteration = state["best"], state["best_iteration"]
        self.history = [tuple(x) for x in state["history"]]
        self.reason = state["reason"]
        self.below = int(state.get("below", 0))   # checkpoints from before patience existed
        self.kept_iteration = int(state.get("kept_iteration", self.best_iteration))
        # checkpoints from before the scatter margin: the judged evaluations are all known
        self.seen = [tuple(x) for x in state.get("seen", state["history"])]


def replay(iterations, values, drop=None, patience=None, start=0, noise=None):
    """(iteration at which ``EarlyStopper(drop, patience, noise)`` would stop on a logged
    series of watched values (None entries skipped), or None; the best iteration).
    ``drop``, ``patience`` and ``noise`` default to ``STOP_RULE``'s (TrainConfig's
    defaults). As in training, only evaluations at iterations >= ``start`` (the end of
    densification) are judged; the earlier ones inform the noise margin."""
    st = EarlyStopper(drop=STOP_RULE.drop if drop is None else drop,
                      patience=STOP_RULE.patience if patience is None else patience,
                      noise=STOP_RULE.noise if noise is None else noise)
    for it, v in zip(iterations, values):
        if v is None:
            continue
        if it < start:
            st.observe(int(it), v)
        elif st.update(int(it), v) == "stop":
            return int(it), st.best_iteration
    return None, st.best_iteration
