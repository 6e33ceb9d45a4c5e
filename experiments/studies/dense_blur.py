"""Voxel-scale noise in gr's volumes of the dense micro-CT cases (issue 21 item 4).

Two questions about a finished ``experiments/studies/dense_volumes.py`` run (its run folder under
$TMPDIR/dense_volumes/runs/CASE/VARIANT):

1. ``heldout CASE VARIANT``: could the held-out views choose a blur of the volume? For the kept state (the best
   held-out state, before the held-out views joined training), the volume blurred by a
   Gaussian of sigma voxels is projected (Joseph) onto the held-out views, and its mean
   squared residual against the measured views is printed beside the 3-D PSNR (oracle).
2. ``filtered CASE SIGMA``: train gr with the field convolved by an isotropic Gaussian of
   SIGMA voxels inside the model (Sigma' = Sigma + s^2 I, densities rescaled to keep each
   kernel's mass; Mip-Splatting's 3-D filter), to see whether a band limit in the model
   removes the noise that a blur of the output removes. Not a training option: the
   filter is patched into the trainer for this run only.

    MI_GRG_DATA=../shared/data TMPDIR=/tmp/dv .venv/bin/python experiments/studies/dense_blur.py \
        heldout bone default
    MI_GRG_DATA=../shared/data TMPDIR=/tmp/dv .venv/bin/python experiments/studies/dense_blur.py \
        filtered bone 0.5

Prints one JSON line per result (collected in docs/bench/dense_blur.json; docs/benchmarks.md,
"Dense micro-CT volumes", quotes them).
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SIGMAS = (0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.85, 1.0)


def _root() -> Path:
    return Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "dense_volumes"


def _case(name: str):
    from mi_grg.lab.runner import suite_case
    from mi_grg.lab.suite import load_suite
    suite = load_suite(ROOT / "experiments" / "suite_cpu.json")
    return suite_case(suite.case(name), _root())


def heldout(name: str, variant: str) -> None:
    import mi_grg  # noqa: F401  (before mitsuba: it picks the variant and LLVM)
    import mitsuba as mi
    from scipy.ndimage import gaussian_filter
    from mi_grg.core.joseph import forward_project
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.voxelizer import voxelize
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training.checkpoint import raw_parameters
    case = _case(name)
    run = _root() / "runs" / name / variant
    info = json.loads((run / "metrics.json").read_text())["method_info"]
    held = info["held_out_views"]
    raw = raw_parameters(run / "checkpoint.npz", "kept")
    with np.load(run / "checkpoint.npz") as z:
        scale = mi.Float(z["kept_density_scale"]) if "kept_density_scale" in z.files else None
    vol = voxelize(Gaussians.from_raw(raw), case.geometry, extent=info["extent"],
                   density_scale=scale)
    final = np.load(run / "vol_pred.npy")
    angles = np.asarray(case.geometry.angles)[held]
    for s in SIGMAS:
        blur = (lambda v: gaussian_filter(v, s)) if s else (lambda v: v)
        kept = blur(vol)      # once: projected and scored
        res = np.mean((forward_project(kept, case.geometry, angles) - case.train[held]) ** 2)
        print(json.dumps({"case": name, "variant": variant, "sigma_vox": s,
                          "kept_iteration": info["kept_iteration"],
                          "heldout_mse_kept": float(res),
                          "psnr_3d_kept": round(float(psnr_3d(kept, case.vol_gt)), 2),
                          "psnr_3d_final": round(float(psnr_3d(blur(final), case.vol_gt)), 2)}))


def filtered(name: str, sigma_vox: float) -> None:
    import mi_grg  # noqa: F401  (before drjit: it picks the variant and LLVM)
    import drjit as dr
    import mi_grg.training.trainer as trainer
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.methods import reconstruct
    from dense_volumes import blur_scores        # this folder's study: on sys.path below
    case = _case(name)
    geo = case.geometry
    sf2 = (sigma_vox * float(np.mean(np.asarray(geo.sVoxel) / np.asarray(geo.nVoxel)))) ** 2

    class Filtered(Gaussians):
        @classmethod
        def from_raw(cls, raw):
            g = Gaussians.from_raw(raw)
            s = g.scales
            s2 = dr.sqrt(s * s + sf2)
            mass = (s.x * s.y * s.z) / (s2.x * s2.y * s2.z)
            return Gaussians(positions=g.positions, scales=s2, rotations=g.rotations,
                             densities=g.densities * mass)

    trainer.Gaussians = Filtered          # this process only
    out = _root() / "runs_filtered" / name / f"sigma{sigma_vox}"
    _, m = reconstruct(case, "gr", out_dir=out, progress=False, log_3d_every=250)
    info = m["method_info"]
    print(json.dumps({"case": name, "filter_sigma_vox": sigma_vox,
                      "psnr_3d": round(m["psnr_3d"], 2), "ssim_3d": round(m["ssim_3d"], 4),
                      "best_heldout_psnr": info["best_heldout_psnr"],
                      "train_s": round(info["train_seconds"], 1),
                      "load_1min": round(os.getloadavg()[0], 2),
                      "blurred": blur_scores(out, case.vol_gt)}))


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    what, name, arg = sys.argv[1:4]
    heldout(name, arg) if what == "heldout" else filtered(name, float(arg))
