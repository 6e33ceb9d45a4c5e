"""Held-out-view stopping and tuning for the iterative classical methods (SART, OS-SART,
ASD-POCS, PDHG): decisions on held-out training views, then the chosen setting on every view.

Protocol (``run_heldout``), never looking at the ground truth:

1. Split the training views with ``mi_grg.data.case.holdout_split`` (one view in every
   ``holdout_every`` held out, evenly spread; TrainConfig's default 8, as gr/r2).
2. For every candidate setting of a small grid (e.g. ASD-POCS's TV weight alpha, PDHG's
   lambda), run the method on the fitted views only; after every sweep (every
   ``eval_every`` iterations) project the volume onto the held-out views and feed their
   PSNR to an ``EarlyStopper`` with TrainConfig's drop / patience / noise / keep (the rule object
   gr and r2 use). It ends the run; its ``kept_iteration`` is that setting's sweep count.
3. With ``discrepancy`` (SART and ASD-POCS), the sweep count comes instead from the
   discrepancy principle (Morozov): the first sweep whose mean squared residual on the
   fitted views is at most the noise level, and the noise level is estimated on the
   held-out views as the lowest mean squared held-out residual any decision run reached
   (their noise is independent of the fit, so no state predicts them better on average;
   the estimate errs high, which stops early rather than late). A candidate whose residual
   never reaches it keeps the EarlyStopper's sweep.
4. Choose the setting whose kept state has the highest held-out PSNR.
5. Run the chosen setting for the chosen sweep count on ALL training views (the held-out
   ones included) and return that volume: the decision used held-out views, the result
   uses every view (issue 26). A sweep over 25 views and one over 21 do about the same
   per view, so the count transfers.

Why step 3: the held-out views measure the error of predicting projections, not the 3-D
error. On noisy sparse views SART's and ASD-POCS's 3-D error grows after a few sweeps
through noise amplified along the weakly projecting (small singular value) directions,
which no projection predicts, so the held-out PSNR keeps rising long after the 3-D PSNR
peaked (it also does when detector pixels instead of views are held out, or when the
held-out residual is ramp-filtered; docs/bench/fair_baselines.md). The fit residual
crossing the noise level marks the peak: fitting beyond it fits noise. PDHG converges to
its TV minimiser instead of semi-converging, and there step 2's rule lands near its best.

Oracle (only when the case has a ground truth, ``oracle`` on): the final run continues
past the chosen sweep and scores the 3-D PSNR of every sweep, to show how close the rule
got to the best sweep chosen with the ground truth. It is labelled "oracle" in the info,
its time (``oracle_seconds``) is left out of metrics.json's "seconds"
(mi_grg.methods.reconstruct) and it decides nothing.
"""
from __future__ import annotations

import time

import numpy as np

#: ``stop`` option values: "heldout" (this protocol) or "none" (a fixed number of sweeps).
STOP_MODES = ("heldout", "none")
#: The oracle keeps scoring sweeps after the chosen one until the 3-D PSNR has stayed below
#: its best for this many sweeps in a row (or the sweep cap is reached).
ORACLE_PATIENCE = 5
ORACLE_LABEL = "oracle: best sweep chosen with the ground truth; decides nothing"


def stop_rule() -> dict:
    """gr's and r2's rule, from TrainConfig's defaults (one place for its numbers)."""
    from mi_grg.training.config import TrainConfig
    c = TrainConfig()
    return {"holdout_every": c.holdout_every, "drop": c.stop_drop,
            "patience": c.stop_patience, "noise": c.stop_noise, "keep": c.keep_state}


def check_stop(stop: str) -> str:
    if stop not in STOP_MODES:
        raise ValueError(f"stop must be one of {', '.join(STOP_MODES)}, got {stop!r}")
    return stop


def _mse(pred: np.ndarray, target: np.ndarray) -> float:
    """Mean squared residual of projections [view, v, u] (line-integral units squared)."""
    return float(np.mean(np.square(pred.astype(np.float64) - target)))


def _split(case, holdout_every: int, name: str):
    from mi_grg.data.case import holdout_split
    n = int(case.geometry.n_views)
    fit, held = holdout_split(n, holdout_every)
    if len(held) == 0 or len(fit) == 0:
        raise ValueError(f"{name}: stop='heldout' needs held-out views, but {n} training "
                         f"view(s) with holdout_every={holdout_every} leave "
                         f"{len(fit)} to fit and {len(held)} to hold out (need >= 2 views); "
                         "pass --option stop=none (and n_iter) for a fixed sweep count")
    return fit, held


def run_heldout(case, run, grid: list, *, max_sweeps: int, name: str, eval_every: int = 1,
                holdout_every: int | None = None, oracle=None, discrepancy: bool = False,
                progress: bool = True):
    """The protocol of the module docstring for one method.

    Args:
        case: the Case (``train`` [view, v, u], ``geometry``, optional ``vol_gt``).
        run: ``run(proj, geometry, n_iter=, callback=, progress=, **setting) -> [x, y, z]``;
            it calls ``callback(iteration, volume)`` after every iteration and stops when
            the callback returns True.
        grid: candidate settings (dicts of options for ``run``), in order of preference
            on ties.
        max_sweeps: cap on iterations per candidate (the rule normally stops earlier).
        name: the method's name for messages.
        eval_every: iterations between held-out evaluations (1 for a SART sweep).
        holdout_every: None = TrainConfig's default (gr's and r2's).
        oracle: score 3-D PSNR of the final run's sweeps (None: when a ground truth exists).
        discrepancy: the sweep count by the discrepancy principle with the noise level
            estimated on the held-out views (step 3; for semi-convergent methods).
    Returns:
        (volume [x, y, z] float32, info dict for metrics.json).
    """
    rule = stop_rule()
    if holdout_every is not None:
        rule["holdout_every"] = int(holdout_every)
    if int(max_sweeps) < 1:
        raise ValueError(f"n_iter (the sweep cap) must be >= 1, got {max_sweeps}")
    if int(eval_every) < 1:
        raise ValueError(f"eval_every must be >= 1, got {eval_every}")
    if not grid:
        raise ValueError(f"{name}: the grid of settings is empty")
    from mi_grg.classical.joseph import forward_project
    from mi_grg.evaluation.metrics import psnr_proj
    from mi_grg.training.early_stop import EarlyStopper
    fit, held = _split(case, rule["holdout_every"], name)
    geo = case.geometry
    angles = np.asarray(geo.angles, np.float64)
    geo_fit = geo.with_angles(angles[fit])
    target = case.train[held]
    fit_data = case.train[fit]
    t_start = time.perf_counter()
    candidates = []
    for setting in grid:
        stopper = EarlyStopper(drop=rule["drop"], patience=rule["patience"],
                               noise=rule["noise"], keep=rule["keep"], label="held-out PSNR")
        last, residuals = [0], []

        def judge(it, vol, stopper=stopper, last=last, residuals=residuals):
            sweep = it + 1
            last[0] = sweep
            if sweep % eval_every:
                return False
            pred = forward_project(vol, geo, angles[held])
            if discrepancy:     # [sweep, held-out MSE, fitted-view MSE]
                residuals.append([sweep, _mse(pred, target),
                                  _mse(forward_project(vol, geo_fit), fit_data)])
            return stopper.update(sweep, psnr_proj(pred, target)) == "stop"

        t0 = time.perf_counter()
        run(fit_data, geo_fit, n_iter=int(max_sweeps), callback=judge,
            progress=progress, **setting)
        if stopper.kept_iteration < 1:
            raise ValueError(f"{name}: no held-out evaluation in {last[0]} iteration(s) "
                             f"(eval_every={eval_every}); raise n_iter")
        values = dict(stopper.history)
        candidates.append({
            "setting": dict(setting), "sweeps_run": last[0],
            "kept_sweep": stopper.kept_iteration,
            "heldout_psnr": values[stopper.kept_iteration],
            "best_heldout_psnr": stopper.best, "best_sweep": stopper.best_iteration,
            "stopped_because": stopper.reason or (
                f"ran to {last[0]} iteration(s) (the cap n_iter={max_sweeps} or the "
                "method's own convergence test) without the rule stopping it"),
            "history": [list(h) for h in stopper.history],
            "seconds": time.perf_counter() - t0})
        if discrepancy:
            candidates[-1]["residuals"] = residuals
    noise = None
    if discrepancy:
        noise = min(h for c in candidates for _, h, _ in c["residuals"])
        for c in candidates:
            k = next((s for s, _, f in c["residuals"] if f <= noise), None)
            c["discrepancy_sweep"] = k
            if k is not None:
                c["kept_sweep"] = k
                c["heldout_psnr"] = dict(c["history"])[k]
    chosen = max(range(len(candidates)), key=lambda i: (candidates[i]["heldout_psnr"], -i))
    pick = candidates[chosen]
    decision_seconds = time.perf_counter() - t_start

    # Final run: the chosen setting and sweep count on every view.
    k = int(pick["kept_sweep"])
    scoring = oracle if oracle is not None else case.vol_gt is not None
    if scoring and case.vol_gt is None:
        raise ValueError(f"{name}: oracle=True needs a ground truth (vol_gt.npy)")
    kept, curve, spent, t_kept = {}, [], [0.0], [None]
    t0 = time.perf_counter()

    def final(it, vol):
        sweep = it + 1
        if sweep == k:
            kept["vol"] = vol
            t_kept[0] = time.perf_counter() - t0 - spent[0]
        if not scoring:
            return sweep >= k
        from mi_grg.evaluation.metrics import psnr_3d
        ts = time.perf_counter()
        if sweep % eval_every == 0 or sweep == k:
            curve.append((sweep, float(psnr_3d(vol, case.vol_gt))))
        spent[0] += time.perf_counter() - ts
        if sweep < k:
            return False
        best = max(p for _, p in curve)
        since = sweep - max(s for s, p in curve if p == best)
        return since >= ORACLE_PATIENCE * eval_every

    cap = int(max_sweeps) if scoring else k
    vol = run(case.train, geo, n_iter=max(k, cap), callback=final, progress=progress,
              **pick["setting"])
    total_final = time.perf_counter() - t0
    if "vol" not in kept:       # the method's own convergence test ended the run first
        kept["vol"], t_kept[0] = vol, total_final - spent[0]
    final_seconds = t_kept[0]
    info = {
        "protocol": "heldout",
        "stop_rule": {**rule, "eval_every": int(eval_every),
                      "rule": "EarlyStopper (mi_grg.training.early_stop), as gr/r2" + (
                          "; sweeps by the discrepancy principle" if discrepancy else "")},
        "decision_views": fit.tolist(), "held_out_views": held.tolist(),
        "final_views": list(range(int(geo.n_views))),
        "candidates": candidates,
        "chosen": {"setting": pick["setting"], "sweeps": k,
                   "heldout_psnr": pick["heldout_psnr"]},
        "why": (f"highest held-out-view PSNR ({pick['heldout_psnr']:.3f} dB on views "
                f"{held.tolist()}) among {len(candidates)} setting(s), at the state "
                + (f"where the fitted views' mean squared residual first reached the "
                   f"noise level {noise:.4g} (the lowest held-out one)"
                   if pick.get("discrepancy_sweep") else "the rule kept")
                + f" (sweep {k}); then run on all {int(geo.n_views)} views for {k} "
                "sweep(s)"),
        "decision_seconds": decision_seconds, "final_seconds": final_seconds,
        "oracle_seconds": total_final - final_seconds,
    }
    if discrepancy:
        info["discrepancy"] = {
            "noise_mse": noise, "tau": 1.0,
            "noise_from": "lowest mean squared held-out-view residual over the decision runs",
            "sweeps": {str(i): c["discrepancy_sweep"] for i, c in enumerate(candidates)}}
    if scoring and curve:
        at = dict(curve)
        best_sweep, best = max(curve, key=lambda c: (c[1], -c[0]))
        info["oracle"] = {"label": ORACLE_LABEL, "best_sweep": best_sweep,
                          "psnr_3d_best": best, "psnr_3d_chosen": at.get(k),
                          "gap_db": best - at[k] if k in at else None,
                          "curve": [list(c) for c in curve]}
    return kept["vol"], info
