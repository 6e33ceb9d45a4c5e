"""Iteration caps that widen until they do not bind.

A fixed cap is a choice like a weight: where a method converges slowly (PDHG at 128^3), a
cap tuned at 64^3 stops every candidate before its held-out views stop improving, and the
method is judged by where the cap fell. ``Widening`` doubles the cap while doubling pays:
at ``base``, 2 ``base``, 4 ``base`` ... the run goes on while the best value of the last
doubling beats the best before it by more than ``gain_db``, up to ``max_factor`` x
``base``. Values are in dB, higher better (held-out PSNR, or -10 log10 of a residual).
"""
from __future__ import annotations

from dataclasses import dataclass

#: The held-out gain (dB) a doubling must bring to earn the next one. Chosen on the tuning
#: cases of experiments/studies/pdhg_rules.py (docs/bench/pdhg_rules.md).
WIDEN_GAIN_DB = 0.05
#: The cap never widens past this multiple of its base (16 x 60 = 960 PDHG iterations).
WIDEN_MAX_FACTOR = 16


@dataclass(frozen=True)
class Widening:
    """A cap that starts at ``base`` iterations and doubles while doubling pays."""

    base: int
    gain_db: float = WIDEN_GAIN_DB
    max_factor: int = WIDEN_MAX_FACTOR

    def __post_init__(self):
        if int(self.base) != self.base or self.base < 1:
            raise ValueError(f"a widening cap's base must be an integer >= 1, got {self.base}")
        if not self.gain_db >= 0:
            raise ValueError(f"gain_db must be >= 0, got {self.gain_db}")
        if int(self.max_factor) != self.max_factor or self.max_factor < 1:
            raise ValueError(f"max_factor must be an integer >= 1, got {self.max_factor}")

    @property
    def ceiling(self) -> int:
        return int(self.base * self.max_factor)

    def goes_on(self, history, sweep: int) -> bool:
        """Whether a run evaluated at ``sweep`` continues; ``history`` holds every
        (sweep, value in dB) so far. Between doublings it always does."""
        sweep = int(sweep)
        if sweep >= self.ceiling:
            return False
        if not self._doubling(sweep):
            return True
        half = sweep // 2
        before = [v for s, v in history if s <= half]
        after = [v for s, v in history if half < s <= sweep]
        if not before or not after:
            return True
        return max(after) - max(before) > self.gain_db

    def binds(self, history, sweep: int) -> bool:
        """Whether a run that ended at ``sweep`` was still paying at the ceiling."""
        if int(sweep) < self.ceiling:
            return False
        half = int(sweep) // 2
        before = [v for s, v in history if s <= half]
        after = [v for s, v in history if half < s <= sweep]
        return bool(before and after and max(after) - max(before) > self.gain_db)

    def _doubling(self, sweep: int) -> bool:
        if sweep < self.base or sweep % self.base:
            return False
        k = sweep // self.base
        return k & (k - 1) == 0

    def record(self) -> dict:
        return {"base": int(self.base), "gain_db": float(self.gain_db),
                "max_factor": int(self.max_factor), "ceiling": self.ceiling,
                "rule": "the cap doubles while the last doubling raised the best held-out "
                        f"value by more than {self.gain_db:g} dB"}
