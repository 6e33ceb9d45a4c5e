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

