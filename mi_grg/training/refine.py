"""A data-consistent total-variation refinement of a trained volume (``refine="tv"``).

The Gaussians fit the projections but leave voxel-scale structure that no view constrains
(docs/findings.md, "Where gr stands"). The refinement solves PDHG's problem

    min_x  1/2 ||A x - b||^2 + lambda TV(x),   0 <= x

(``mi_grg.classical.pdhg``) starting from the voxelised field, so that it keeps the
field's structure where the data and the prior agree and removes what neither asks for.
All decisions use the run's own split (``mi_grg.protocol.heldout``), no ground truth:

1. the weight: the one PDHG's protocol chooses for these data (candidates from zero on
   the fitted views, the one-standard-error rule on the held-out views);
2. the iteration count: PDHG at that weight from the state the run kept before the
   held-out views joined training, on the fitted views, stopped by the held-out views; the
   start itself is a candidate (0 iterations: no refinement);
3. that many iterations from the final state, on every view.

Why the weight is not searched from the start as well: from a fitted volume the held-out
views favour ever weaker weights, whose iterations fit the voxel-scale noise back in
(docs/benchmarks.md, "TV refinement"). The same blind spot remains in step 2: on some
scans the held-out views prefer a refinement that lowers the 3-D PSNR (measured there).

``gaussians.npz`` / ``.ply`` of a refined run hold the field before refinement: the
refined volume is a voxel grid.
"""
from __future__ import annotations

import numpy as np

from mi_grg.classical.pdhg import reconstruct_pdhg


def refine_tv(trainer, progress: bool = True) -> tuple:
    """(volume [x, y, z] float32, info) for a finished ``Trainer``: its final volume refined
    as the module docstring says, or unchanged with the reason in ``info["skipped"]`` when
    nothing can decide (no held-out views, or no state kept before they joined)."""
    final = trainer.volume()
    st, held = trainer.state, trainer.held_idx
    if len(held) == 0:
        return final, {"skipped": "no held-out views to decide on (holdout_every=0)"}
    if st.kept_raw is None:
        return final, {"skipped": "no state kept before the held-out views joined"}
    kept = trainer.volume(st.kept_raw, st.kept_density_scale)
    vol, info = refine_volume(trainer.case, kept, final,
                              holdout_every=trainer.cfg.protocol.holdout_every,
                              progress=progress)
    if not np.array_equal(np.asarray(info["held_out_views"]), np.asarray(held)):
        raise RuntimeError("refine: the decision's held-out views differ from training's")
    return vol, info


def refine_volume(case, kept: np.ndarray, final: np.ndarray, *, holdout_every: int,
                  progress: bool = True) -> tuple:
    """Steps 1-3 of the module docstring for volumes [x, y, z]: ``kept`` (never fitted to
    the held-out views of ``holdout_every``) decides, ``final`` is refined. Returns
    (volume float32, info)."""
    split = {"holdout_every": holdout_every, "oracle": False, "progress": progress}
    _, weight = reconstruct_pdhg(case, final=False, **split)
    lam = weight["chosen"]["setting"]["lam"]
    vol, info = reconstruct_pdhg(case, lam=lam, start=(kept, final), **split)
    return np.asarray(vol, np.float32), {
        "lam": lam, "iterations": info["chosen"]["sweeps"], "why": info["why"],
        "held_out_views": info["held_out_views"],
        "weight_search": weight.get("search"),
        "weight_candidates": [{"lam": c["setting"]["lam"], "iterations": c["kept_sweep"],
                               "heldout_psnr": c["heldout_psnr"]}
                              for c in weight["candidates"]],
        "heldout_psnr": {"start": info["candidates"][0]["history"][0][1],
                         "refined": info["chosen"]["heldout_psnr"]},
        "decision_seconds": weight["decision_seconds"] + info["decision_seconds"],
        "final_seconds": info["final_seconds"]}
