"""A CT case in memory: geometry, train/test projections, optional ground truth."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mi_grg.core.geometry import Geometry


@dataclass
class Case:
    """One scan, as ``mi_grg.load_case`` returns it and ``save_case`` writes it.

    Attributes:
        geometry:    scan geometry whose ``angles`` are the training angles (radians).
        train:       training projections [view, v, u], float32 line integrals.
        test_angles: test angles [view] (radians); may be empty.
        test:        test projections [view, v, u] (noise-free in simulated cases).
        vol_gt:      ground-truth density [x, y, z] or None.
        scene_scale: factor by which lengths and projections were multiplied on load
                     (R2-Gaussian's 2 / max(sVoxel)); 1.0 for data in file units.
                     Densities are not affected by it.
        info:        what produced the data (phantom, noise model and parameters, ...),
                     echoed into metrics.json.
        clamped:     what ``load_case`` repaired: per split ("proj_train", "proj_test"),
                     ``{"count": values set to 0, "min": most negative value, "tolerance":
                     NEG_TOL_REL x max}`` in file units; empty when nothing was clamped.
                     Echoed into metrics.json; not written by ``save_case``.
    """

    geometry: Geometry
    train: np.ndarray
    test_angles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    test: np.ndarray | None = None
    vol_gt: np.ndarray | None = None
    scene_scale: float = 1.0
    info: dict = field(default_factory=dict)
    clamped: dict = field(default_factory=dict)

    @property
    def test_geometry(self) -> Geometry:
        if len(self.test_angles) == 0:
            raise ValueError("this case has no test views")
        return self.geometry.with_angles(self.test_angles)


def holdout_split(n_views: int, holdout_every: int) -> tuple:
    """(fit, held) view indices [n - k], [k]: one view in every ``holdout_every`` is held out
    for decisions (early stopping, choosing a setting) and never fitted while it decides;
    0 holds out none. The one formula gr, r2 and the classical methods share.

    The k = ceil(n / holdout_every) held-out views sit at the middles of k equal blocks of
    the view list, floor((j + 1/2) n / k): evenly spread, so that the widest gap the fitted
    views leave is the narrowest any k held-out views allow (two steps while k < n / 2,
    when neither end of the arc is held out). Why not views 0, n, 2n, ... as before: on a
    full circle the last of those (24 of 25 with n = 8) is view 0's neighbour, a three-step
    gap; on the shell case (gr, 25 views) holding out {0, 8, 16, 24} cost 1.05 dB against
    holding out none, {0, 13} 1.1 dB, {0} alone 0.5 dB, and {3, 9, 15, 21} nothing
    (docs/benchmarks.md, "Every view counts")."""
    n, every = int(n_views), int(holdout_every)
    if every < 0:
        raise ValueError(f"holdout_every must be >= 0 (0: no held-out views), got {every}")
    k = -(-n // every) if every else 0
    held = np.zeros(n, bool)
    held[(np.arange(k) * 2 + 1) * n // (2 * k) if k else []] = True
    return np.flatnonzero(~held), np.flatnonzero(held)
