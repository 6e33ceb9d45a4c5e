"""A regularisation weight chosen on held-out views: a 1-D search on a log grid that
widens past whichever end wins, so that the chosen weight is interior to what was tried
(a weight at the edge of its grid says only that the grid was too narrow)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

#: How ``run_heldout`` picks the winning value: the best held-out PSNR; the largest value
#: within one standard error of it; or the largest value whose fitted-view residual, where
#: its run settles, is at most the noise level the held-out views measure (Morozov).
RULES = {"best": "best held-out PSNR", "one_se": "one standard error",
         "morozov": "Morozov's discrepancy principle"}


@dataclass
class LogGrid:
    """Candidate values of one weight ``name`` (> 0, ascending), widened one step at a time
    past the end that wins, at most ``max_extend`` steps per end. The step beyond an end is
    the ratio of the two values at that end (a half-decade grid stays one).

    Usage: run every value of ``values``; ``next_value(winner)`` gives the next value to
    run (None: the winner is interior, or the widening is spent); ``record(winner)``
    says what was searched, for metrics.json."""

    name: str
    values: list
    max_extend: int = 4
    rule: str = "best"         # which value wins: a key of RULES (mi_grg.protocol.heldout)
    added: dict = field(default_factory=lambda: {"below": 0, "above": 0})

    def __post_init__(self):
        v = [float(x) for x in self.values]
        if len(v) < 2:
            raise ValueError(f"{self.name}: a grid needs at least two values to search, got "
                             f"{self.values!r} (give one number to fix the weight)")
        if not all(math.isfinite(x) and x > 0 for x in v):
            raise ValueError(f"{self.name}: grid values must be finite and > 0, got {v}")
        if any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"{self.name}: grid values must be distinct, got {v}")
        if int(self.max_extend) != self.max_extend or self.max_extend < 0:
            raise ValueError(f"{self.name}: max_extend must be an integer >= 0, got "
                             f"{self.max_extend}")
        if self.rule not in RULES:
            raise ValueError(f"{self.name}: rule must be one of {', '.join(RULES)}, got "
                             f"{self.rule!r}")
        self.values = sorted(v)

    def settings(self) -> list:
        return [{self.name: v} for v in self.values]

    def next_value(self, winner: float):
        """The value to try next given the current ``winner`` (None: search done)."""
        v = self.values
        if winner == v[0] and self.added["below"] < self.max_extend:
            self.added["below"] += 1
            new = v[0] * v[0] / v[1]
        elif winner == v[-1] and self.added["above"] < self.max_extend:
            self.added["above"] += 1
            new = v[-1] * v[-1] / v[-2]
        else:
            return None
        self.values = sorted(v + [new])
        return new

    def record(self, winner: float) -> dict:
        interior = self.values[0] < winner < self.values[-1]
        return {"weight": self.name, "values_tried": list(self.values), "chosen": winner,
                "interior": interior, "added_below": self.added["below"],
                "added_above": self.added["above"], "max_extend": int(self.max_extend),
                "rule": RULES[self.rule]}
