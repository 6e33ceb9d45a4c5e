"""CT measurement noise: TIGRE's ``CTnoise.add`` as R2-Gaussian used it for its data sets.

TIGRE (``Python/tigre/utilities/CTnoise.py``) turns line integrals ``p`` [view, v, u]
into noisy ones as follows, normalising by the largest value ``m = max(p)`` of the whole
stack passed in (so the most attenuated pixel sees ``I0 / e`` photons on average,
whatever the object's units):

    counts = Poisson(I0 * exp(-p / m)) + Normal(mean 0, electronic_std)
    noisy  = -log(counts / I0) * m              (float32)

R2-Gaussian calls it with ``Poisson=1e4, Gaussian=[0, 10]`` on the training projections
only and then sets negative results to 0 (``clip_negative``). Differences from TIGRE, both
only where TIGRE would return NaN/Inf: counts are floored at ``COUNT_FLOOR`` = 1 photon
before the log (so ``noisy <= m * log(I0)``; never reached for I0 >= 1e2 and the default
electronic noise), and a stack whose maximum is <= 0 (nothing attenuates) is normalised
by 1 instead of its maximum.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

COUNT_FLOOR = 1.0   # photons; counts below (incl. <= 0 from electronic noise) are raised to it


@dataclass(frozen=True)
class NoiseModel:
    """Poisson photon noise plus Gaussian electronic noise (TIGRE's CTnoise model).

    Attributes:
        I0:             mean photon count of an unattenuated ray (> 0), before the
                        max-normalisation described in the module docstring.
        electronic_std: standard deviation of the additive Gaussian electronic noise, in
                        photon counts (>= 0; mean 0 as in R2-Gaussian's setting).
        clip_negative:  set negative noisy line integrals to 0 (R2-Gaussian's post-step).
    """

    I0: float = 1e4
    electronic_std: float = 10.0
    clip_negative: bool = True

    def __post_init__(self):
        for name in ("I0", "electronic_std"):
            v = getattr(self, name)
            if isinstance(v, bool):
                raise ValueError(f"{name} must be a number, got {v!r}")
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {v!r}") from None
            if not math.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        if self.I0 <= 0:
            raise ValueError(f"I0 (photons per unattenuated ray) must be > 0, got {self.I0}")
        if self.electronic_std < 0:
            raise ValueError(f"electronic_std (photon counts) must be >= 0, got "
                             f"{self.electronic_std}")
        if not isinstance(self.clip_negative, (bool, np.bool_)):
            raise ValueError(f"clip_negative must be a bool, got {self.clip_negative!r}")
        object.__setattr__(self, "clip_negative", bool(self.clip_negative))

    def apply(self, proj, rng: np.random.Generator) -> np.ndarray:
        """Noisy copy of line integrals ``proj`` [view, v, u] (any shape works), float32.

        The normalisation uses the maximum of the whole ``proj`` array, as TIGRE does for
        the stack it is given; pass all training views at once to match R2-Gaussian."""
        p = np.asarray(proj, dtype=np.float64)
        if p.size == 0:
            return p.astype(np.float32)
        if not np.all(np.isfinite(p)):
            raise ValueError("proj must be finite line integrals [view, v, u]")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        m = float(p.max())
        if m <= 0:
            m = 1.0   # nothing attenuates: TIGRE would divide by zero
        counts = rng.poisson(self.I0 * np.exp(-p / m)).astype(np.float64)
        if self.electronic_std > 0:
            counts += rng.normal(0.0, self.electronic_std, size=p.shape)
        noisy = -np.log(np.maximum(counts, COUNT_FLOOR) / self.I0) * m
        if self.clip_negative:
            noisy = np.maximum(noisy, 0.0)
        return noisy.astype(np.float32)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "NoiseModel":
        """Inverse of ``to_dict``; unknown keys raise ``ValueError`` naming them."""
        if not isinstance(d, dict):
            raise ValueError(f"noise settings must be a dict, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown noise setting(s) {unknown}; known: {sorted(known)}")
        return cls(**d)
