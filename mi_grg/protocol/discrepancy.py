"""The noise level measured on held-out views and the discrepancy principle (Morozov).

Held-out views are never fitted, so their residual is the model's prediction error plus
the measurement noise; no state predicts independent noise better on average, so the
lowest mean squared held-out residual any state reaches estimates the noise level from
above. Fitting the fitted views more closely than that fits their noise: the
discrepancy principle stops at the first state whose mean squared fitted-view residual
is at most ``tau`` x the noise level. Residuals are in line-integral units squared
(projections [view, v, u] of -log I / I0), whatever the data set's length unit.
"""
from __future__ import annotations

import math

import numpy as np


def mse(pred: np.ndarray, target: np.ndarray) -> float:
    """Mean squared residual of projections [view, v, u], in float64."""
    return float(np.mean(np.square(np.asarray(pred, np.float64) - target)))


def noise_level(heldout_mse) -> float:
    """The noise level (a mean squared residual) from held-out residuals: their minimum.
    It errs high, which stops a fit early rather than late."""
    values = [float(v) for v in heldout_mse]
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"held-out residuals must be finite and >= 0, got {values[:5]}")
    return min(values)


def discrepancy_stop(fit_mse, noise: float, tau: float = 1.0):
    """The first iteration whose fitted-view residual reaches the noise level.

    Args:
        fit_mse: (iteration, mean squared fitted-view residual) pairs in run order.
        noise: ``noise_level``'s estimate; tau: the principle's safety factor (>= 1
            stops earlier is the classical choice; 1 is the plain principle).
    Returns:
        the iteration, or None when no residual reaches ``tau`` x ``noise``.
    """
    if not (math.isfinite(tau) and tau > 0):
        raise ValueError(f"tau must be a finite number > 0, got {tau}")
    return next((int(i) for i, f in fit_mse if f <= tau * noise), None)
