"""The reconstruction contract shared by every method.

``reconstruct(case, method, out_dir)`` runs a method on a ``Case`` and writes
    OUT/vol_pred.npy   float32 [x, y, z], same shape, axis order and units as vol_gt.npy
    OUT/vol_pred.tif   the same as an ImageJ TIFF stack with its voxel size (``formats``)
    OUT/metrics.json   method, options, wall-clock seconds (a resumed run's whole: the
                       earlier calls' method_info["resumed_seconds"] included), psnr_3d /
                       ssim_3d (with a ground truth), the scanner geometry, what the data
                       set simulated, what load_case clamped, variant and machine
    OUT/slices.png     central orthogonal slices: prediction, ground truth, |error|
A method is a function ``(case, **options) -> np.ndarray [x, y, z]`` or
``-> (np.ndarray, info dict)``; unknown options raise. A method that takes an ``out_dir``
keyword gets the output directory (for checkpoints and logs); ``info`` lands in
metrics.json under "method_info".
"""
from __future__ import annotations

import importlib
import inspect
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from mi_grg.data.case import Case
from mi_grg.data.dataset import json_default

# name -> "module:function"; imported on use so that one method's import cost (or a
# missing optional dependency) never affects the others.
METHODS: dict = {
    "fdk": "mi_grg.classical.fdk:reconstruct_fdk",
    "sart": "mi_grg.classical.iterative:reconstruct_sart",
    "asd-pocs": "mi_grg.classical.iterative:reconstruct_asd_pocs",
    "pdhg": "mi_grg.classical.pdhg:reconstruct_pdhg",
    "r2": "mi_grg.training.trainer:reconstruct_r2",
    "gr": "mi_grg.training.trainer:reconstruct_gr",
}


def available_methods() -> list:
    return sorted(METHODS)


def get_method(name: str):
    """The callable registered under ``name``."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of {available_methods()}")
    target = METHODS[name]
    if callable(target):
        return target
    module, func = target.split(":")
    return getattr(importlib.import_module(module), func)


def register_method(name: str, func) -> None:
    """Add a method (a callable ``(case, **options) -> [x, y, z]``) under ``name``."""
    if not callable(func):
        raise TypeError("func must be callable")
    METHODS[name] = func


# What "+dirty" looks at: the code and configs that produce a result, not the result files
# (docs/bench/*.json, docs/results.md) that a benchmark rewrites while it runs.
CODE_PATHS = ("mi_grg", "plugins", "scenes", "bench", "experiments", "pyproject.toml")


def code_version(root: Path | None = None) -> str:
    """mi_grg's version and, when it runs from a git checkout, the commit ("0.1.0+g1a2b3c4",
    "+dirty" with uncommitted changes to tracked files under CODE_PATHS): which code
    produced a result. root: the checkout (default: the one holding this package)."""
    import subprocess
    from mi_grg import __version__
    root = Path(__file__).resolve().parent.parent if root is None else Path(root)
    try:
        git = ["git", "-C", str(root)]
        commit = subprocess.run(git + ["rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10)
        if commit.returncode != 0:
            return __version__
        dirty = subprocess.run(git + ["status", "--porcelain", "--untracked-files=no", "--",
                                      *CODE_PATHS], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):   # no git, or a hung one
        return __version__
    tag = f"{__version__}+g{commit.stdout.strip()}"
    return tag + ("+dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")


def machine_info() -> dict:
    import mitsuba as mi
    import drjit as dr
    return {"variant": mi.variant(), "mitsuba": mi.__version__, "drjit": dr.__version__,
            "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "python": platform.python_version(), "mi_grg": code_version()}


def geometry_info(case: Case) -> dict:
    """The scan the method saw, in the data set's (file) units as meta_data.json states it:
    TIGRE scanner fields, the number of training/test angles and R2-Gaussian's
    ``scene_scale`` (the factor the method's lengths and projections were multiplied by)."""
    s = float(case.scene_scale)
    g = case.geometry if s == 1.0 else case.geometry.scaled(1.0 / s)   # as save_case does
    return {**g.to_scanner_dict(), "n_angles": int(g.n_views),
            "n_test_angles": int(len(case.test_angles)), "scene_scale": s,
            "per_view": bool(g.per_view)}


def score(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> dict:
    """3-D PSNR / SSIM in the R2-Gaussian convention (data range 1 for normalised data;
    ``mi_grg.data.units.data_range`` gives a case's)."""
    from mi_grg.evaluation.metrics import psnr_3d, ssim_3d
    return {"psnr_3d": float(psnr_3d(pred, gt, data_range)),
            "ssim_3d": float(ssim_3d(pred, gt, data_range))}


def reconstruct(case: Case | str | os.PathLike, method: str, out_dir=None, formats=None,
                staged_for=None, **options):
    """Run ``method`` on ``case`` (a Case or a data-set directory).

    Returns (volume [x, y, z] float32, metrics dict). Writes the contract's files when
    ``out_dir`` is given, the volume in ``formats`` (``mi_grg.data.export``; default npy
    and tiff). ``staged_for``: the folder that ``out_dir`` (a temporary) becomes once the
    run is done (``mi_grg.data.outputs.replaced_dir``), recorded as the run's out_dir.
    """
    from mi_grg.data.export import parse_formats
    formats = parse_formats(formats)   # a bad name fails before any work
    if not isinstance(case, Case):
        from mi_grg.data.dataset import load_case
        case = load_case(case)
    func = get_method(method)
    params = inspect.signature(func).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        # Say which option is wrong here rather than let a TypeError escape from the call.
        unknown = sorted(set(options) - set(params))
        if unknown:
            takes = sorted(k for k in params if k not in ("case", "out_dir"))
            raise ValueError(f"method {method!r} does not take option(s) {unknown}; its "
                             f"options are {takes}")
    check_memory(case, method, options)
    if case.vol_gt is not None and not np.max(case.vol_gt, initial=0.0) > 0:
        raise ValueError("the data set's ground truth (vol_gt) has no voxel above 0, so 3-D "
                         "PSNR / SSIM against it are undefined; leave it out of "
                         "meta_data.json (\"vol\") to reconstruct without scores")
    if out_dir is not None and "out_dir" in params:
        options = {**options, "out_dir": str(out_dir)}
    from mi_grg.data.units import data_range, scaled_case, unit_scale
    t0 = time.perf_counter()
    # Physical units (1/mm): the method sees densities of order 1, the result gets the unit
    # back; normalised cases run unchanged (s = 1). See mi_grg.data.units.
    s = unit_scale(case)
    result = func(scaled_case(case, s), **options)
    seconds = time.perf_counter() - t0
    vol, info = result if isinstance(result, tuple) else (result, None)
    vol = np.asarray(vol, dtype=np.float32) * np.float32(s)
    expected = tuple(case.geometry.nVoxel)
    if vol.shape != expected:
        raise RuntimeError(f"method {method!r} returned shape {vol.shape}, expected nVoxel "
                           f"[x, y, z] = {expected}")
    if not np.all(np.isfinite(vol)):
        raise RuntimeError(f"method {method!r} returned NaN/Inf voxels")
    # An oracle's sweeps and scoring (ground truth; they decide nothing) are not the
    # method's time: method_info["oracle_seconds"] (mi_grg.protocol.heldout).
    seconds -= float((info or {}).get("oracle_seconds") or 0.0)
    # A resumed run (gr / r2 with resume) reports the whole run: the calls before too.
    seconds += float((info or {}).get("resumed_seconds") or 0.0)
    if staged_for is not None and "out_dir" in options:
        options = {**options, "out_dir": str(staged_for)}
    metrics = {"method": method, "options": options, "seconds": seconds,
               "n_train_views": int(case.geometry.n_views), "nVoxel": list(expected),
               "geometry": geometry_info(case),
               # {} says that nothing was clamped; see mi_grg.data.dataset.NEG_TOL_REL
               "clamped_negatives": dict(case.clamped),
               "data": case.info, "machine": machine_info()}
    if info is not None:
        metrics["method_info"] = info
    if s != 1.0:
        metrics["unit_scale"] = s   # densities the method saw = file densities / s
    if case.vol_gt is not None:
        rng, rule = data_range(case, case.vol_gt)
        metrics.update(score(vol, case.vol_gt, rng))
        metrics["psnr_data_range"], metrics["psnr_data_range_rule"] = rng, rule
        if case.info.get("reference"):   # e.g. a pseudo ground truth (FDK of all views)
            metrics["ground_truth"] = case.info["reference"]
    if out_dir is not None:
        write_outputs(out_dir, vol, metrics, case.vol_gt, formats=formats)
    return vol, metrics


#: Float32 copies of the volume each method holds at once (result, accumulators, the
#: TV and dual variables; gr's TV refinement runs PDHG on its voxelised result).
VOLUME_COPIES = {"fdk": 4, "sart": 6, "asd-pocs": 8, "pdhg": 10, "r2": 6, "gr": 10}
TRAINED_METHODS = ("r2", "gr")


def check_memory(case: Case, method: str, options: dict) -> None:
    """Refuse (one line naming the sizes and --max-memory) a run whose volume copies,
    projections and, for a trained method, Gaussians and projector plans would not fit
    (``mi_grg.core.memory``), before any of them is allocated."""
    from mi_grg.core import memory
    g = case.geometry
    needs = [memory.volume(g.nVoxel, VOLUME_COPIES.get(method, 6)),
             memory.projections(g.n_views + len(case.test_angles), g.nDetector, copies=4)]
    if method in TRAINED_METHODS:
        from mi_grg.core import projector
        from mi_grg.training.config import TrainConfig
        cap = options.get("max_gaussians", TrainConfig().densify.max_gaussians)
        needs += [memory.gaussians(cap if isinstance(cap, int) else 0),
                  memory.plans(projector.RECORDS_PER_CHUNK, projector.ROWS_PER_BATCH,
                               projector.PIXELS_PER_CHUNK)]
    memory.check(needs, f"--method {method} on nVoxel {list(g.nVoxel)}",
                 lower="lower nVoxel (a coarser volume) or the detector size")


def write_outputs(out_dir, vol: np.ndarray, metrics: dict, vol_gt=None, formats=None) -> Path:
    """Write vol_pred in ``formats`` (default .npy and an ImageJ .tif, with the voxel size
    of metrics["geometry"]; ``mi_grg.data.export``), metrics.json and slices.png into
    ``out_dir``."""
    from mi_grg.data.export import write_case_volume
    from mi_grg.evaluation.plotting import slice_montage
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = write_case_volume(out, "vol_pred", vol, metrics["geometry"],
                              (metrics.get("data") or {}).get("units") or {}, formats)
    # what mi_grg.lab.finished reads back before a run counts as finished
    metrics["volume_files"] = [p.name for p in files]
    with open(out / "metrics.json", "w") as f:
        json.dump(metrics, f, indent=2, default=json_default)
    title = metrics.get("method", "")
    if "psnr_3d" in metrics:
        title += f"   PSNR {metrics['psnr_3d']:.2f} dB   SSIM {metrics['ssim_3d']:.3f}"
    slice_montage(out / "slices.png", vol, vol_gt, title=title)
    return out
