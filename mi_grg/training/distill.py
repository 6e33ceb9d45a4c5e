"""Fitting Gaussians to a voxel grid: how a refined volume goes back into the field.

The TV refinement (``mi_grg.training.result``) works on a grid; so that what a run
exports is what it scores, the refined grid is fitted back into the Gaussians it started
from. The fit minimises the mean squared difference between the Gaussians' voxelisation
and the grid, by Adam on the raw parameters (densities stay positive through their
softplus), from Gaussians that already match the grid up to the refinement's change:

    min_G  mean((V(G) - x)^2)

with V the voxelizer (``mi_grg.core.voxelizer.voxelize_dr``, differentiable). It stops
once V(G) matches x to ``FIT_STOP_DB`` (PSNR over x's range), checked every
``CHECK_EVERY`` steps. Its fidelity (that PSNR) is recorded: a refinement that adds mass
where no Gaussian is cannot be fitted, and the record shows it.
"""
from __future__ import annotations

import math

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry

#: Fidelity (dB) at which the fit stops: far below the noise of any reconstruction.
FIT_STOP_DB = 55.0
#: Steps between fidelity checks (each check is one voxelisation without derivatives).
CHECK_EVERY = 25


def fidelity_db(vol: np.ndarray, target: np.ndarray) -> float:
    """PSNR (dB) of ``vol`` against ``target`` over the target's range (inf if equal)."""
    mse = float(np.mean((np.asarray(vol, np.float64) - target) ** 2))
    peak = float(np.ptp(target)) or 1.0
    return math.inf if mse == 0 else 10.0 * math.log10(peak * peak / mse)


def fit_to_volume(g: Gaussians, geometry: Geometry, target: np.ndarray, *, lr: dict,
                  iterations: int, extent: float, progress: bool = True,
                  on_check=None) -> tuple:
    """(Gaussians, info) fitted to ``target`` [x, y, z] from ``g`` (module docstring).

    ``lr``: Adam's initial rates per raw group (``mi_grg.training.optim``), decaying to a
    tenth over ``iterations``. ``info``: iterations run and the fidelity before and after.
    ``on_check(iteration, Gaussians, fidelity_db)``, if given, is called at every check
    (research records: bench/fit_back.py).
    """
    from tqdm import tqdm
    from mi_grg.core.voxelizer import voxelize
    from mi_grg.training.optim import Adam
    target = np.ascontiguousarray(target, np.float32)
    if target.shape != tuple(geometry.nVoxel):
        raise ValueError(f"target has shape {target.shape}, the grid is "
                         f"{tuple(geometry.nVoxel)}")
    start_db = fidelity_db(voxelize(g, geometry, extent=extent), target)
    info = {"iterations": 0, "fidelity_db_start": start_db, "fidelity_db": start_db}
    if iterations < 1 or len(g) == 0 or start_db >= FIT_STOP_DB:
        return g, info
    x = mi.TensorXf(mi.Float(target.reshape(-1)), target.shape)
    opt = Adam(lr=lr, max_steps=iterations)
    raw = g.to_raw()
    for v in raw.values():
        dr.enable_grad(v)
    best = (start_db, g)
    with tqdm(total=iterations, desc="fit to the refined volume", disable=not progress,
              leave=False) as bar:
        for it in range(1, iterations + 1):
            loss = _loss(Gaussians.from_raw(raw), geometry, x, extent)
            dr.backward(loss)
            raw = opt.step(raw)
            bar.update(1)
            if it % CHECK_EVERY == 0 or it == iterations:
                fit = Gaussians.from_raw({k: dr.detach(v) for k, v in raw.items()})
                db = fidelity_db(voxelize(fit, geometry, extent=extent), target)
                info.update(iterations=it, fidelity_db=db)
                if on_check is not None:
                    on_check(it, fit, db)
                if db > best[0]:
                    best = (db, fit)
                if db >= FIT_STOP_DB:
                    break
    info["fidelity_db"] = best[0]
    return best[1], info


def _loss(g: Gaussians, geometry: Geometry, x, extent: float):
    from mi_grg.core.voxelizer import voxelize_dr
    d = voxelize_dr(g, geometry, extent=extent) - x
    return dr.mean(dr.square(d.array))
