"""A data-consistent total-variation refinement of a trained volume (``refine="tv"``).

The Gaussians fit the projections but leave voxel-scale structure that no view constrains
(docs/findings.md, "Where gr stands"). The refinement solves PDHG's problem

    min_x  1/2 ||A x - b||^2 + lambda TV(x),   0 <= x

(``mi_grg.classical.pdhg``) starting from the voxelised field, so that it keeps the
field's structure where the data and the prior agree and removes what neither asks for.
Its decisions use the run's own split (``mi_grg.protocol.heldout``), never the ground
truth. PDHG starts from the state the run kept before the held-out views joined training
and runs on the fitted views only, once per weight of PDHG's grid (widened past a winning
end), to its iteration cap:

1. the weight: Morozov's discrepancy principle, the largest weight whose fitted-view
   residual where its run settles is at most the noise level, the lowest held-out residual
   of any state (the start's included);
2. the iteration count: that weight's sweep with the lowest held-out residual, the start
   itself a candidate (0 iterations: no refinement);
3. that many iterations at that weight from the final state, on every view.

Why not PDHG's own choice by the held-out PSNR: from a start that already fits the data,
the held-out views' PSNR keeps rising under a weak weight that fits noise back into
directions no view sees (on some scans the 3-D PSNR fell by several dB meanwhile); the
fitted residual falling below the noise level is what shows it (docs/benchmarks.md, "TV
refinement").

Without held-out views (``holdout_every=0``: every view trained from the start) no state of
the run is unseen by any view, so a *decision run* decides instead: the same configuration
with the stop rule's split (one view in 8 held out until 2/3 of the schedule), whose kept
state takes the place of the run's in steps 1-2; step 3 refines the run's own final state.
It costs a second training; a scan too small for that split is returned unrefined, and the
record says why.

``gaussians.npz`` / ``.ply`` of a refined run hold the field before refinement: the
refined volume is a voxel grid.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from mi_grg.classical.pdhg import reconstruct_pdhg


def refine_tv(trainer, progress: bool = True) -> tuple:
    """(volume [x, y, z] float32, info) for a finished ``Trainer``: its final volume refined
    as the module docstring says, or unchanged with the reason in ``info["skipped"]`` when
    nothing can decide (no state kept before the held-out views joined; without held-out
    views, no decision run possible)."""
    final = trainer.volume()
    st, held = trainer.state, trainer.held_idx
    if len(held) == 0:
        return _refine_by_decision_run(trainer, final, progress)
    if st.kept_raw is None:
        return final, {"skipped": "no state kept before the held-out views joined"}
    kept = trainer.volume(st.kept_raw, st.kept_density_scale)
    vol, info = refine_volume(trainer.case, kept, final,
                              holdout_every=trainer.cfg.protocol.holdout_every,
                              progress=progress)
    if not np.array_equal(np.asarray(info["held_out_views"]), np.asarray(held)):
        raise RuntimeError("refine: the decision's held-out views differ from training's")
    return vol, info


def _refine_by_decision_run(trainer, final: np.ndarray, progress: bool) -> tuple:
    """``refine_tv`` for a run without held-out views: the decision run's kept state
    decides, ``final`` is refined. ``info["decision_run"]`` records it."""
    kept, record = decision_run(trainer, progress)
    if kept is None:
        return final, {"skipped": record["skipped"]}
    vol, info = refine_volume(trainer.case, kept, final, holdout_every=record["holdout_every"],
                              progress=progress)
    info["decision_run"] = record
    return vol, info


def decision_run(trainer, progress: bool = True) -> tuple:
    """(kept volume [x, y, z] or None, record) of the decision run (module docstring) for a
    finished run without held-out views; None with the reason in ``record["skipped"]``
    when none can be made (a time_budget, too few views for the split, no kept state)."""
    from mi_grg.protocol.early_stop import STOP_RULE
    from mi_grg.protocol.split import decision_split
    from mi_grg.training.config import TrainConfig
    every = STOP_RULE.holdout_every
    why = "no held-out views to decide on (holdout_every=0), and "
    if trainer.cfg.run.time_budget is not None:
        return None, {"skipped": why + "a decision run would train past the time_budget"}
    try:
        decision_split(trainer.case.geometry.n_views, every, "refine=tv's decision run")
    except ValueError as e:
        return None, {"skipped": why + str(e)}
    cfg = TrainConfig.from_flat({**trainer.cfg.to_flat(), "holdout_every": every,
                                 "refine": "none"})
    print(f"refine=tv with holdout_every=0: a decision run (holdout_every={every}) decides "
          "the refinement; it trains a second time", file=sys.stderr)
    t0 = time.perf_counter()
    # type(trainer), not an import: the trainer module imports this one
    run = type(trainer)(trainer.case, cfg, progress=progress)
    summary = run.run()
    if run.state.kept_raw is None:
        return None, {"skipped": why + "the decision run kept no state before its views "
                                       "joined"}
    kept = run.volume(run.state.kept_raw, run.state.kept_density_scale)
    return kept, {"holdout_every": every, "seconds": time.perf_counter() - t0,
                  "kept_iteration": summary["kept_iteration"],
                  "held_out_views": run.held_idx.tolist()}


def refine_volume(case, kept: np.ndarray, final: np.ndarray, *, holdout_every: int,
                  progress: bool = True) -> tuple:
    """Steps 1-3 of the module docstring for volumes [x, y, z]: ``kept`` (never fitted to
    the held-out views of ``holdout_every``) decides, ``final`` is refined. Returns
    (volume float32, info)."""
    vol, info = reconstruct_pdhg(case, lam_rule="morozov", start=(kept, final),
                                 holdout_every=holdout_every, oracle=False, progress=progress)
    start, chosen = info["candidates"][0], info["chosen"]
    return np.asarray(vol, np.float32), {
        "lam": chosen["setting"]["lam"], "iterations": chosen["sweeps"], "why": info["why"],
        "held_out_views": info["held_out_views"], "weight_search": info.get("search"),
        "noise_mse": info["morozov"]["noise_mse"],
        "weight_candidates": [{"lam": c["setting"]["lam"], "iterations": c["kept_sweep"],
                               "heldout_mse": c["heldout_mse"],
                               "settled_fit_mse": c["settled_fit_mse"]}
                              for c in info["candidates"]],
        "heldout_psnr": {"start": start["history"][0][1],
                         "refined": chosen["heldout_psnr"]},
        "heldout_mse": {"start": start["residuals"][0][1],
                        "refined": next(c["heldout_mse"] for c in info["candidates"]
                                        if c["setting"] == chosen["setting"])},
        "decision_seconds": info["decision_seconds"], "final_seconds": info["final_seconds"]}
