"""Decide on the fitted views, then run the decision on all views: held-out-view stopping
and tuning for the iterative classical methods (SART, ASD-POCS, PDHG).

Protocol (``run_heldout``), never looking at the ground truth:

1. Split the training views with ``mi_grg.protocol.split.decision_split`` (one view in
   every ``holdout_every`` held out, evenly spread; ``STOP_RULE``'s 8, as gr/r2).
2. For every candidate setting (a list, or a ``LogGrid`` of one weight, e.g. ASD-POCS's
   TV weight alpha, PDHG's lam, which widens past a winning end: ``mi_grg.protocol.search``),
   run the method on the fitted views only; after every sweep (every
   ``eval_every`` iterations) project the volume onto the held-out views and feed their
   PSNR to an ``EarlyStopper`` with ``STOP_RULE``'s drop / patience / noise / keep (the rule
   gr and r2 use). It ends the run; its ``kept_iteration`` is that setting's sweep count.
3. With ``discrepancy`` (SART and ASD-POCS), the sweep count comes instead from the
   discrepancy principle (Morozov): the first sweep whose mean squared residual on the
   fitted views is at most the noise level, and the noise level is estimated on the
   held-out views (``mi_grg.protocol.discrepancy``). A candidate whose residual
   never reaches it keeps the EarlyStopper's sweep.
4. Choose the setting whose kept state has the highest held-out PSNR (or the largest
   weight within one standard error of it), or by Morozov's discrepancy principle: the
   largest weight whose fitted-view residual, where its run settles at the cap, is at most
   the noise level, each candidate kept at its lowest held-out residual (``_morozov``).
5. Run the chosen setting for the chosen sweep count on ALL training views (the held-out
   ones included) and return that volume: the decision used held-out views, the result
   uses every view. A sweep over 25 views and one over 21 do about the same
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

import dataclasses
import sys
import time
from dataclasses import dataclass

import numpy as np

from mi_grg.evaluation.metrics import psnr_3d, psnr_proj_views
from mi_grg.protocol.discrepancy import discrepancy_stop, mse, noise_level
from mi_grg.protocol.early_stop import STOP_RULE, StopRule
from mi_grg.protocol.search import LogGrid
from mi_grg.protocol.split import decision_split
from mi_grg.protocol.widening import Widening

#: ``stop`` option values: "heldout" (this protocol) or "none" (a fixed number of sweeps).
STOP_MODES = ("heldout", "none")
#: The oracle keeps scoring sweeps after the chosen one until the 3-D PSNR has stayed below
#: its best for this many sweeps in a row (or the sweep cap is reached).
ORACLE_PATIENCE = 5
ORACLE_LABEL = "oracle: best sweep chosen with the ground truth; decides nothing"


def stop_rule() -> dict:
    """The rule's settings as metrics.json records them."""
    return dataclasses.asdict(STOP_RULE)


def check_stop(stop: str) -> str:
    if stop not in STOP_MODES:
        raise ValueError(f"stop must be one of {', '.join(STOP_MODES)}, got {stop!r}")
    return stop


@dataclass
class _Decision:
    """The fitted / held-out views of one case and what the decision runs need."""
    case: object
    project: object        # (volume [x, y, z], geometry, angles) -> [view, v, u]
    fit: np.ndarray
    held: np.ndarray
    eval_every: int
    discrepancy: bool
    start: tuple | None = None   # (decision runs' start volume, final run's) or None
    morozov: bool = False        # the weight by Morozov's rule (``_morozov``)
    widening: Widening | None = None   # the cap doubles while doubling pays

    def __post_init__(self):
        geo = self.case.geometry
        self.angles = np.asarray(geo.angles, np.float64)
        self.geo_fit = geo.with_angles(self.angles[self.fit])
        self.target = self.case.train[self.held]
        self.fit_data = self.case.train[self.fit]


def _decision_run(d: _Decision, run, setting: dict, rule: StopRule, max_sweeps: int,
                  name: str, progress: bool) -> dict:
    """One candidate on the fitted views, judged after every ``eval_every`` sweeps."""
    stopper = rule.stopper()
    last, residuals, per_view = [0], [], []
    geo = d.case.geometry

    def judge(it, vol):
        sweep = it + 1
        last[0] = sweep
        if sweep % d.eval_every:
            return False
        pred = d.project(vol, geo, d.angles[d.held])
        if d.discrepancy or d.morozov:     # [sweep, held-out MSE, fitted-view MSE]
            residuals.append([sweep, mse(pred, d.target),
                              mse(d.project(vol, d.geo_fit, d.geo_fit.angles), d.fit_data)])
        views = psnr_proj_views(pred, d.target)
        per_view.append([sweep, views.tolist()])
        stop = stopper.update(sweep, float(np.nanmean(views))) == "stop"
        if d.widening is not None and not d.widening.goes_on(stopper.history, sweep):
            return True
        return stop and not d.morozov     # Morozov reads where the run settles: the cap

    t0 = time.perf_counter()
    warm = {}
    if d.start is not None:     # the start is sweep 0: a candidate may keep it unchanged
        judge(-1, d.start[0])
        warm = {"init": d.start[0]}
    cap = int(max_sweeps) if d.widening is None else d.widening.ceiling
    run(d.fit_data, d.geo_fit, n_iter=cap, callback=judge, progress=progress,
        **setting, **warm)
    if stopper.kept_iteration < (0 if d.start is not None else 1):
        raise ValueError(f"{name}: no held-out evaluation in {last[0]} iteration(s) "
                         f"(eval_every={d.eval_every}); raise n_iter")
    values = dict(stopper.history)
    c = {"setting": dict(setting), "sweeps_run": last[0],
         "kept_sweep": stopper.kept_iteration,
         "heldout_psnr": values[stopper.kept_iteration],
         "best_heldout_psnr": stopper.best, "best_sweep": stopper.best_iteration,
         "stopped_because": stopper.reason or (
             f"ran to {last[0]} iteration(s) (the cap n_iter={cap} or the "
             "method's own convergence test) without the rule stopping it"),
         "history": [list(h) for h in stopper.history],
         "heldout_psnr_views": per_view,
         "seconds": time.perf_counter() - t0}
    if d.discrepancy or d.morozov:
        c["residuals"] = residuals
    if d.discrepancy:
        c["rule_sweep"] = c["kept_sweep"]
    if d.widening is not None:
        c["cap_binds"] = d.widening.binds(stopper.history, last[0])
    return c


def _choose(candidates: list, discrepancy: bool, rule: str = "best",
            from_start: bool = False):
    """(index of the chosen candidate, noise level or None); ``rule``: a key of
    ``mi_grg.protocol.search.RULES`` ("morozov": ``_morozov``). With ``discrepancy`` each
    candidate's sweep becomes its discrepancy sweep where its residual reaches the noise
    level (re-judged whenever candidates are added: the level is a minimum over all).
    With rule "one_se" the choice is the one-standard-error rule (``_one_se``). With
    ``from_start`` (runs from a given start) a candidate kept at sweep 0 is the start
    itself, whatever its weight: it ranks below every candidate that regularised it."""
    if rule == "morozov":
        return _morozov(candidates)
    noise = None
    if discrepancy:
        noise = noise_level(h for c in candidates for _, h, _ in c["residuals"])
        for c in candidates:
            k = discrepancy_stop([(s, f) for s, _, f in c["residuals"]], noise)
            c["discrepancy_sweep"] = k
            c["kept_sweep"] = k if k is not None else c["rule_sweep"]
            c["heldout_psnr"] = dict(map(tuple, c["history"]))[c["kept_sweep"]]
    order = sorted(range(len(candidates)), key=lambda i: (
        bool(candidates[i]["kept_sweep"]) or not from_start,
        _sort_key(candidates[i]["setting"])))
    best = max(order, key=lambda i: (candidates[i]["heldout_psnr"], -order.index(i)))
    return (_one_se(candidates, order, best) if rule == "one_se" else best), noise


def _morozov(candidates: list):
    """(index, noise level): Morozov's discrepancy principle for the weight, the lowest
    held-out residual for the sweeps. The noise level is the lowest mean squared held-out
    residual of any state (``noise_level``); the weight is the largest one whose fitted-view
    residual where its run settled (the last sweep) is at most that level, since a larger
    one cannot fit the data to their noise; the smallest when none can. Each candidate's
    state is its sweep with the lowest held-out mean squared residual (the start, sweep 0,
    included). Why not the held-out PSNR: from a start that already fits the data (a
    refinement), projections of the held-out views improve while a too weak weight fits
    noise into directions no view sees; the fitted residual falling below the noise level
    shows it (`git show d7f240b:docs/benchmarks.md`, "TV refinement")."""
    noise = noise_level(h for c in candidates for _, h, _ in c["residuals"])
    for c in candidates:
        s, h, _ = min(c["residuals"], key=lambda r: (r[1], r[0]))
        c["kept_sweep"], c["heldout_mse"] = int(s), h
        c["heldout_psnr"] = dict(map(tuple, c["history"]))[c["kept_sweep"]]
        c["settled_fit_mse"] = c["residuals"][-1][2]
    order = sorted(range(len(candidates)), key=lambda i: _sort_key(candidates[i]["setting"]))
    fits = [i for i in order if candidates[i]["settled_fit_mse"] <= noise]
    return (fits[-1] if fits else order[0]), noise


def _one_se(candidates: list, order: list, best: int) -> int:
    """The one-standard-error rule of cross-validation (Hastie, Tibshirani & Friedman,
    ESL 7.10): of the candidates whose held-out PSNR lies within one standard error of the
    best's, the one with the largest weight. Why: held-out views predict projections, and
    weaker regularisation keeps improving that prediction a little while the 3-D error
    grows in directions no projection sees; the standard error (the spread of the best
    state's per-view PSNRs over sqrt(views)) says which differences the held-out views can
    tell apart at all."""
    c = candidates[best]
    views = dict((s, v) for s, v in map(tuple, c["heldout_psnr_views"]))[c["kept_sweep"]]
    v = np.asarray([x for x in views if np.isfinite(x)], np.float64)
    se = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) > 1 else 0.0
    level = c["heldout_psnr"] - se
    within = [i for i in order if candidates[i]["heldout_psnr"] >= level]
    for i, cand in enumerate(candidates):
        cand["within_one_se"] = i in within
    c["one_se"] = {"standard_error_db": se, "level_db": level}
    return within[-1]


def _sort_key(setting: dict):
    """Candidates compare in the order of their values (ties go to the first)."""
    return tuple(setting[k] for k in sorted(setting))


def _decide(d: _Decision, run, grid, rule, max_sweeps, name, progress):
    """Every candidate of ``grid`` (a list of settings or a ``LogGrid``), widening a
    LogGrid past a winning end. Returns (candidates, chosen index, noise, search record)."""
    search = grid if isinstance(grid, LogGrid) else None
    pending = search.settings() if search else list(grid)
    candidates = []
    while pending:
        for setting in pending:
            candidates.append(_decision_run(d, run, setting, rule, max_sweeps, name,
                                            progress))
        chosen, noise = _choose(candidates, d.discrepancy, search.rule if search else "best",
                                d.start is not None)
        winner = candidates[chosen]["setting"].get(search.name) if search else None
        if d.start is not None and candidates[chosen]["kept_sweep"] == 0 and not d.morozov:
            winner = None       # the start itself won: no weight to search past
        nxt = search.next_value(winner) if search else None
        pending = [] if nxt is None else [{search.name: nxt}]
    record = search.record(candidates[chosen]["setting"][search.name]) if search else None
    return candidates, chosen, noise, record


def _final_run(case, run, pick: dict, max_sweeps: int, eval_every: int, scoring: bool,
               progress: bool, start=None):
    """The chosen setting for its sweep count on every view (from ``start`` when given;
    0 sweeps return it unchanged); with ``scoring`` (the oracle) the run goes on past it,
    scoring the 3-D PSNR of each sweep. Returns (volume at the chosen sweep, its seconds
    without scoring, total seconds, oracle curve)."""
    k = int(pick["kept_sweep"])
    warm = {} if start is None else {"init": start}
    if k == 0 and not scoring:
        return np.asarray(start, np.float32), 0.0, 0.0, []
    kept, curve, spent, t_kept = {}, [], [0.0], [None]
    if k == 0:
        kept["vol"], t_kept[0] = np.asarray(start, np.float32), 0.0
        curve.append((0, float(psnr_3d(start, case.vol_gt))))
    t0 = time.perf_counter()

    def final(it, vol):
        sweep = it + 1
        if sweep == k:
            kept["vol"] = vol
            t_kept[0] = time.perf_counter() - t0 - spent[0]
        if not scoring:
            return sweep >= k
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
    vol = run(case.train, case.geometry, n_iter=max(k, cap), callback=final,
              progress=progress, **pick["setting"], **warm)
    total = time.perf_counter() - t0
    if "vol" not in kept:       # the method's own convergence test ended the run first
        kept["vol"], t_kept[0] = vol, total - spent[0]
    return kept["vol"], t_kept[0], total, curve


def oracle_info(curve: list, k: int) -> dict:
    """The oracle's record of a run scored at (sweep, 3-D PSNR) points ``curve``, whose
    result is sweep ``k``: its best sweep (the earliest of equals) and the gap to it."""
    at = dict(curve)
    best_sweep, best = max(curve, key=lambda c: (c[1], -c[0]))
    return {"label": ORACLE_LABEL, "best_sweep": best_sweep, "psnr_3d_best": best,
            "psnr_3d_chosen": at.get(k), "gap_db": best - at[k] if k in at else None,
            "curve": [list(c) for c in curve]}


def _why(pick: dict, held: list, n_candidates: int, noise, k: int, n_views: int) -> str:
    if "settled_fit_mse" in pick:
        fits = pick["settled_fit_mse"] <= noise
        return ((f"the largest of {n_candidates} weight(s) whose fitted-view mean squared "
                 "residual where its run settled" if fits else f"the smallest of "
                 f"{n_candidates} weight(s), since none settled with a fitted-view mean "
                 "squared residual") + f" ({pick['settled_fit_mse']:.4g}) at most the noise "
                f"level {noise:.4g} (the lowest held-out one; Morozov), at its sweep with the "
                f"lowest held-out residual on views {held} (sweep {k}); then run on all "
                f"{n_views} views for {k} sweep(s)")
    state = (f"where the fitted views' mean squared residual first reached the noise level "
             f"{noise:.4g} (the lowest held-out one)" if pick.get("discrepancy_sweep")
             else "the rule kept")
    return (f"highest held-out-view PSNR ({pick['heldout_psnr']:.3f} dB on views {held}) "
            f"among {n_candidates} setting(s), at the state {state} (sweep {k}); then run "
            f"on all {n_views} views for {k} sweep(s)")


def _noise_info(candidates: list, noise, d: _Decision) -> dict:
    """What the noise level decided: each weight's settled fit (Morozov) or each
    candidate's discrepancy sweep; {} when neither rule ran."""
    if not (d.morozov or d.discrepancy):
        return {}
    record = {"noise_mse": noise, "tau": 1.0, "noise_from": "lowest mean squared "
              "held-out-view residual over the decision runs"}
    if d.morozov:
        return {"morozov": {**record, "settled_fit_mse": {
            str(_sort_key(c["setting"])[0]): c["settled_fit_mse"] for c in candidates}}}
    return {"discrepancy": {**record, "sweeps": {
        str(i): c["discrepancy_sweep"] for i, c in enumerate(candidates)}}}


def _cap_info(widening: Widening, pick: dict, name: str) -> dict:
    """The widened cap's record; stderr says when it still bound the chosen candidate."""
    if pick.get("cap_binds"):
        print(f"{name}: the held-out PSNR still rose at the widened cap of "
              f"{widening.ceiling} iterations; pass n_iter to run longer", file=sys.stderr)
    return {**widening.record(), "binds": bool(pick.get("cap_binds"))}


def _check_args(name, grid, max_sweeps, eval_every, start, discrepancy) -> None:
    if isinstance(grid, LogGrid) and grid.rule == "morozov" and discrepancy:
        raise ValueError(f"{name}: the discrepancy sweep rule and Morozov's weight rule "
                         "exclude each other")
    if int(max_sweeps) < 1:
        raise ValueError(f"n_iter (the sweep cap) must be >= 1, got {max_sweeps}")
    if int(eval_every) < 1:
        raise ValueError(f"eval_every must be >= 1, got {eval_every}")
    if not isinstance(grid, LogGrid) and not grid:
        raise ValueError(f"{name}: the grid of settings is empty")
    if start is not None and len(start) != 2:
        raise ValueError(f"{name}: start must be (decision volume, final volume)")


def run_heldout(case, run, grid, *, project, max_sweeps: int, name: str,
                eval_every: int = 1, holdout_every: int | None = None, oracle=None,
                discrepancy: bool = False, start=None, widen: bool = False,
                progress: bool = True):
    """The protocol of the module docstring for one method.

    Args:
        case: the Case (``train`` [view, v, u], ``geometry``, optional ``vol_gt``).
        run: ``run(proj, geometry, n_iter=, callback=, progress=, **setting) -> [x, y, z]``;
            it calls ``callback(iteration, volume)`` after every iteration and stops when
            the callback returns True.
        grid: candidate settings (a list of option dicts for ``run``, ties going to the
            first in value order) or a ``LogGrid`` of one weight (its ``rule`` chooses;
            under "morozov" every candidate runs to ``max_sweeps``).
        project: ``project(volume [x, y, z], geometry, angles) -> [view, v, u]``, the
            method's own forward model (predictions of the held-out views).
        max_sweeps: cap on iterations per candidate (the rule normally stops earlier);
            with ``widen`` the cap's base, doubled while doubling pays
            (``mi_grg.protocol.widening``).
        name: the method's name for messages.
        eval_every: iterations between held-out evaluations (1 for a SART sweep).
        holdout_every: None = ``STOP_RULE``'s (gr's and r2's).
        oracle: score 3-D PSNR of the final run's sweeps (None: when a ground truth exists).
        discrepancy: the sweep count by the discrepancy principle with the noise level
            estimated on the held-out views (step 3; for semi-convergent methods).
        start: None, or (decision start, final start): volumes [x, y, z] that ``run``
            starts from (its ``init`` option), for refining another method's result. The
            decision runs' start must not have been fitted to the held-out views. The
            start itself is a candidate (sweep 0: kept unchanged).
        widen: the cap widens until it does not bind (``Widening(max_sweeps)``).
    Returns:
        (volume [x, y, z] float32, info dict for metrics.json).
    """
    rule = STOP_RULE if holdout_every is None else StopRule(holdout_every=int(holdout_every))
    _check_args(name, grid, max_sweeps, eval_every, start, discrepancy)
    scoring = oracle if oracle is not None else case.vol_gt is not None
    if scoring and case.vol_gt is None:
        raise ValueError(f"{name}: oracle=True needs a ground truth (vol_gt.npy)")
    fit, held = decision_split(case.geometry.n_views, rule.holdout_every, name)
    morozov = isinstance(grid, LogGrid) and grid.rule == "morozov"
    widening = Widening(int(max_sweeps)) if widen else None
    d = _Decision(case, project, fit, held, int(eval_every), discrepancy,
                  None if start is None else tuple(start), morozov, widening)
    t_start = time.perf_counter()
    candidates, chosen, noise, search = _decide(d, run, grid, rule, max_sweeps, name,
                                                progress)
    pick = candidates[chosen]
    decision_seconds = time.perf_counter() - t_start
    k = int(pick["kept_sweep"])
    vol, final_seconds, total_final, curve = _final_run(
        case, run, pick, max_sweeps if widening is None else widening.ceiling,
        int(eval_every), scoring, progress, None if start is None else start[1])
    n = int(case.geometry.n_views)
    info = {
        "protocol": "heldout",
        "stop_rule": {**stop_rule(), "holdout_every": rule.holdout_every,
                      "eval_every": int(eval_every),
                      "rule": "EarlyStopper (mi_grg.protocol.early_stop), as gr/r2" + (
                          "; sweeps by the discrepancy principle" if discrepancy else "")},
        "decision_views": fit.tolist(), "held_out_views": held.tolist(),
        "final_views": list(range(n)),
        "candidates": candidates,
        "chosen": {"setting": pick["setting"], "sweeps": k,
                   "heldout_psnr": pick["heldout_psnr"]},
        "why": (("the largest weight within one standard error of the " if search and
                 search["rule"] == "one standard error" else "") +
                _why(pick, held.tolist(), len(candidates), noise, k, n)),
        "decision_seconds": decision_seconds, "final_seconds": final_seconds,
        "oracle_seconds": total_final - final_seconds,
    }
    if search is not None:
        info["search"] = search
    if widening is not None:
        info["cap"] = _cap_info(widening, pick, name)
    info.update(_noise_info(candidates, noise, d))
    if scoring and curve:
        info["oracle"] = oracle_info(curve, k)
    return vol, info
