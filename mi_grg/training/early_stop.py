"""Early stopping without ground truth: watch the PSNR of held-out training views.

The paper evaluates PSNR every 500 iterations and stops "if the PSNR decreases by more than
0.5 %". We compare with the BEST value so far (not only the previous one), so a slow slide
of several small drops also stops the run; the caller keeps a state (see below).

``patience`` is the number of evaluations in a row that must lie below that margin
(1 = the paper's rule as written). At our scaled schedules (12 evaluations in 1500
iterations rather than 60 in 30k) the held-out PSNR still rises late in training and
wobbles around that trend by about the margin itself, so a single dip ended runs that
recovered at the next evaluation (docs/benchmarks.md, "Measurements behind defaults").
TrainConfig's default is 2.

Which state to keep (``TrainConfig.keep_state``): the same wobble makes "the state with the
highest held-out PSNR" an early state by chance, with a worse 3-D PSNR than a later state
within the margin (docs/benchmarks.md, "Reconstruction"). "latest" (the default) therefore
keeps the LATEST state whose value lies within ``drop`` of the best (the stop rule's own
noise margin: it does not call such a state worse); "best" keeps the literal maximum. ``EarlyStopper.kept_iteration`` names the state to hold.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

#: Which state a run keeps (``TrainConfig.keep_state``, ``EarlyStopper.keep``).
KEEP_STATES = ("latest", "best")


@dataclass
class EarlyStopper:
    """Stop when ``value < best * (1 - drop)`` at ``patience`` evaluations in a row; ``drop``
    is a fraction (0.005 = 0.5 %).

    ``update`` returns "improved" (a new best), "within" (below the best by at most ``drop``),
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

    def __post_init__(self):
        if not 0 <= self.drop < 1:
            raise ValueError(f"drop must be a fraction in [0, 1), got {self.drop}")
        if int(self.patience) != self.patience or self.patience < 1:
            raise ValueError(f"patience must be an integer >= 1, got {self.patience}")
        if self.keep not in KEEP_STATES:
            raise ValueError(f"keep must be one of {', '.join(KEEP_STATES)}, got {self.keep!r}")

    def update(self, iteration: int, value: float) -> str:
        if not math.isfinite(value):
            # An infinite PSNR means an exact fit (improvement); NaN is a failure.
            if math.isnan(value):
                raise FloatingPointError(f"{self.label} is NaN at iteration {iteration}")
        self.history.append((int(iteration), float(value)))
        if value > self.best:
            self.best, self.best_iteration = float(value), int(iteration)
            self.below, self.kept_iteration = 0, int(iteration)
            return "improved"
        # PSNR can be negative in dB only for hopeless fits; use the magnitude for the margin.
        if value >= self.best - self.drop * abs(self.best):
            self.below = 0
            if self.keep == "latest":
                self.kept_iteration = int(iteration)
            return "within"
        self.below += 1
        if self.below < self.patience:
            return "below"
        row = (f" ({self.patience} evaluations in a row)" if self.patience > 1 else "")
        self.reason = (f"{self.label} fell from {self.best:.3f} (iteration "
                       f"{self.best_iteration}) to {value:.3f} at iteration {iteration}, "
                       f"a drop of more than {100 * self.drop:g} %{row}")
        return "stop"

    def state_dict(self) -> dict:
        """The evaluation state (JSON-serialisable); the settings (drop, patience, keep,
        label) are the constructor's."""
        return {"best": self.best, "best_iteration": self.best_iteration,
                "kept_iteration": self.kept_iteration,
                "history": list(self.history), "reason": self.reason, "below": self.below}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output."""
        self.best, self.best_iteration = state["best"], state["best_iteration"]
        self.history = [tuple(x) for x in state["history"]]
        self.reason = state["reason"]
        self.below = int(state.get("below", 0))   # checkpoints from before patience existed
        self.kept_iteration = int(state.get("kept_iteration", self.best_iteration))
