"""Early stopping without ground truth: watch the PSNR of held-out training views.

The paper evaluates PSNR every 500 iterations and stops "if the PSNR decreases by more than
0.5 %". We compare with the BEST value so far (not only the previous one), so a slow slide
of several small drops also stops the run, and the caller keeps the best state.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class EarlyStopper:
    """Stop when ``value < best * (1 - drop)``; ``drop`` is a fraction (0.005 = 0.5 %).

    ``update`` returns one of "improved", "continue" or "stop"; ``reason`` says why the run
    stopped ("held-out PSNR fell ..."), ``best`` / ``best_iteration`` where it peaked.
    """

    drop: float = 0.005
    label: str = "held-out PSNR"
    best: float = -math.inf
    best_iteration: int = -1
    history: list = field(default_factory=list)
    reason: str | None = None

    def __post_init__(self):
        if not 0 <= self.drop < 1:
            raise ValueError(f"drop must be a fraction in [0, 1), got {self.drop}")

    def update(self, iteration: int, value: float) -> str:
        if not math.isfinite(value):
            # An infinite PSNR means an exact fit (improvement); NaN is a failure.
            if math.isnan(value):
                raise FloatingPointError(f"{self.label} is NaN at iteration {iteration}")
        self.history.append((int(iteration), float(value)))
        if value > self.best:
            self.best, self.best_iteration = float(value), int(iteration)
            return "improved"
        # PSNR can be negative in dB only for hopeless fits; use the magnitude for the margin.
        if value < self.best - self.drop * abs(self.best):
            self.reason = (f"{self.label} fell from {self.best:.3f} (iteration "
                           f"{self.best_iteration}) to {value:.3f} at iteration {iteration}, "
                           f"a drop of more than {100 * self.drop:g} %")
            return "stop"
        return "continue"

    def state(self) -> dict:
        return {"best": self.best, "best_iteration": self.best_iteration,
                "history": list(self.history), "reason": self.reason}

    def load_state(self, state: dict) -> None:
        self.best, self.best_iteration = state["best"], state["best_iteration"]
        self.history = [tuple(x) for x in state["history"]]
        self.reason = state["reason"]
