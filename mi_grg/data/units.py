"""Which units a case is in, and the internal rescaling that makes every method unit-free.

A case states its units in ``case.info["units"]`` (written by ``mi-grg import``)::

    {"length": "mm", "density": "1/mm", "normalised": false}

A case without that block (every simulated case, every R2-Gaussian data set) is in
R2-Gaussian's normalised units: densities in about [0, 1]. Two things depend on it:

* metrics: PSNR/SSIM take data range 1 on normalised data and the ground truth's maximum
  otherwise (``data_range``);
* training: gr/r2 thresholds (De-Init's tau, the density initialisation, learning rates,
  pruning) are calibrated for densities of order 1. A case in physical units is divided by
  ``unit_scale`` (a robust maximum of its FDK) before a method runs and the result is
  multiplied back (``methods.reconstruct``), so that no threshold depends on the unit.
  Normalised cases are left exactly as they are (scale 1), so their results do not move.
"""
from __future__ import annotations

import dataclasses

import numpy as np

#: Percentile of the FDK that defines the density scale: a robust maximum (streaks and
#: single hot voxels of a sparse-view FDK sit above it).
SCALE_PERCENTILE = 99.9


def units_of(case) -> dict:
    """The case's units block; the normalised default when it states none."""
    units = (case.info or {}).get("units")
    if units is None:
        return {"length": "normalised", "density": "normalised", "normalised": True}
    if not isinstance(units, dict) or not isinstance(units.get("normalised"), bool):
        raise ValueError(f"case info 'units' must be an object with a boolean 'normalised', "
                         f"got {units!r}")
    return units


def is_normalised(case) -> bool:
    return bool(units_of(case)["normalised"])


def data_range(case, gt: np.ndarray) -> tuple:
    """(PSNR/SSIM data range, the rule in words): 1 for normalised data, else max(gt)."""
    if is_normalised(case):
        return 1.0, "1 (normalised densities, R2-Gaussian's convention)"
    peak = float(np.max(gt))
    if not np.isfinite(peak) or peak <= 0:
        raise ValueError(f"the ground truth's maximum is {peak}; a PSNR data range needs "
                         "a positive maximum (case in physical units)")
    unit = units_of(case).get("density", "?")
    return peak, f"max of the ground truth ({peak:.4g} {unit}; data in physical units)"


def fdk_scale(proj: np.ndarray, geometry) -> float:
    """A robust maximum (``SCALE_PERCENTILE``) of the FDK of ``proj`` in ``geometry``."""
    from mi_grg.core.fdk import fdk
    vol = fdk(proj, geometry)
    s = float(np.percentile(vol, SCALE_PERCENTILE))
    if not np.isfinite(s) or s <= 0:
        raise ValueError(f"the FDK of the training projections has a {SCALE_PERCENTILE}th "
                         f"percentile of {s}; cannot normalise the density unit (are the "
                         "projections line integrals -log(I/I0)?)")
    return s


def unit_scale(case) -> float:
    """The factor a method's input is divided by: 1 for normalised cases, else the FDK's
    robust maximum (densities of the scaled case are then of order 1)."""
    if is_normalised(case):
        return 1.0
    return fdk_scale(case.train, case.geometry)


def scaled_case(case, s: float):
    """A copy of ``case`` with projections and ground truth divided by ``s``: densities in
    units of ``s``, of order 1, so the copy counts as normalised (scaling it again is a
    no-op). ``case`` itself is not changed."""
    if s == 1.0:
        return case
    inv = np.float32(1.0 / s)
    units = units_of(case)
    return dataclasses.replace(
        case, train=case.train * inv,
        test=None if case.test is None else case.test * inv,
        vol_gt=None if case.vol_gt is None else case.vol_gt * inv,
        info={**case.info, "unit_scale": float(s),
              "units": {**units, "normalised": True,
                        "density": f"{float(s):.6g} {units.get('density', '')}".strip()}})
