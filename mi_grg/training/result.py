"""What a trained run returns and exports: one field, voxel-averaged and refined.

After training, a gr run's result is made in three steps, each optional, and the volume
it scores (vol_pred) is always the voxelisation of the Gaussians it exports:

1. **Voxel average** (``voxel_average`` = f > 0): the returned field is blurred by f times
   a voxel's box variance (``mi_grg.core.voxel_average``), so that its voxelisation at
   voxel centres holds voxel averages, as the ground truth of a scan does. With
   ``field_blur="heldout"`` the held-out views add a share of their own
   (``field_share``): the state kept before they joined training, blurred by each share
   of ``BLUR_SHARES``, projected onto them; the share with the lowest residual is added
   to f (variances add). That blur removes the field's own noise, which the views see;
   the voxel's box is a property of the ground truth's grid, which they do not see, so
   f stays fixed.
2. **TV refinement** (``refine="tv"``): PDHG (``mi_grg.classical.pdhg``) solves

       min_x  1/2 ||A x - b'||^2 + lambda TV(x),   0 <= x,   b' = b - (P(G) - A V(G))

   from x = V(G), G the field, V its voxelisation, P its exact projections, A the Joseph
   projector. The *anchor* P(G) - A V(G) is the difference between the two forward models
   on the field itself: without it, the field's start has the residual of the Joseph
   model's error (at 64^3 several times the noise), and the refinement's first iterations
   fit that error instead of the data. With it, the start's residual is the field's own.
   The weight is ``refine_lam``; the length is the held-out choice: from the state kept
   before the held-out views joined training, PDHG on the fitted views, the first
   iteration count whose held-out residual is within the share ``refine_tol`` of the
   curve's lowest (0 included: no refinement; ``refine_tol`` 0: the lowest itself), within
   ``refine_max_iterations`` (the record says when that cap binds; the curve stops
   ``PATIENCE`` checks after its last new minimum). Where the residual hardly falls, its
   minimum lies far along a flat curve on which the grid drifts toward TV's answer
   unseen by the views; the tolerance stops before. ``refine_fall`` < 1 takes the first
   count at which that share of the residual's fall is made, if that comes earlier. That many
   iterations then run from the returned field on every view. Without held-out views a
   decision run supplies the kept state (``decision_run``).
   The anchor helps where a voxel grid misses what the field resolves (thin needles, sharp
   edges) and costs where the field carries voxel-scale noise (dense micro-CT volumes).
   ``refine_anchor="auto"`` refines plain (b' = b) where densification did not meet the
   field's demand (``mi_grg.training.densify.demand``: the count still grew at the end of
   its window, or reached the cap): such a field does not resolve the object, and its
   sub-voxel content, which the anchor carries, is not the object's. Elsewhere it decides
   the length both with the anchor and without it and refines with the form whose
   held-out residual is lower: both residuals predict the same measured views (A x plus
   the anchor, or A x alone). "on" / "off" fix the form.
3. **Back into the Gaussians** (``refine_output="gaussians"``): the refined grid is
   fitted by the field it started from (``mi_grg.training.distill``); vol_pred is that
   field's voxelisation. ``refine_output="voxels"`` returns the grid itself and exports
   the Gaussians under ``EXPORT_STEMS["voxels"]``, a name that says they are not it.

Every decision uses the run's own views; the ground truth only enters the research record
``parts`` (each step's 3-D PSNR, when the case has one), never a choice.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from mi_grg.core.gaussians import Gaussians

#: The exported Gaussians' file stem for each ``refine_output``: "gaussians" when they are
#: the scored result, another name when the result is a grid they are not.
EXPORT_STEMS = {"gaussians": "gaussians", "voxels": "gaussians_before_voxel_step"}
#: Detector tiles per side of a held-out view (``tile_means``).
TILES = 8
#: PDHG iterations between held-out checks of the refinement's length.
CHECK_EVERY = 5
#: Checks without a new minimum of the held-out residual after which the length decision
#: stops (0: it runs to the cap). Replayed on both forms' curves of the Table 1 runs, 6 to
#: 10 change no decision and save about a third of the decision's iterations
#: (docs/benchmarks.md, "The length decision's patience").
PATIENCE = 8
#: Views projected at once by the field's exact projector (bounds its memory).
VIEW_CHUNK = 5
#: The shares of a voxel's box variance that ``field_blur="heldout"`` chooses among
#: (docs/benchmarks.md, "The voxel average's strength": the dense volumes' views choose
#: 1-3, the phantoms' 0).
BLUR_SHARES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)


def finish(trainer, progress: bool = True) -> tuple:
    """(vol_pred [x, y, z] float32, exported Gaussians, info) of a finished ``Trainer``
    (module docstring); ``info["export"]`` names the export's stem."""
    cfg = trainer.cfg.protocol
    t0 = time.perf_counter()
    # the kept state only where a step reads it (its graph field is rebuilt to make it)
    kept, decided_by, decider = (kept_field(trainer, progress) if cfg.refine == "tv"
                                 else (None, {}, None))
    share, blur = field_share(trainer, kept, decider)
    field = averaged_field(trainer, trainer.field_gaussians(), share)
    info = {"voxel_average": blur,
            "export": {"stem": EXPORT_STEMS["gaussians"], "is_result": True}}
    parts = _Parts(trainer)
    parts.add("gaussians", trainer.volume)
    vol = field_volume(trainer, field)
    parts.add("voxel_averaged", vol)
    if cfg.refine == "tv":
        if kept is None:
            info["refine"] = {"skipped": decided_by["skipped"]}
            print(f"refine=tv did nothing: {decided_by['skipped']}; the trained field is "
                  "returned unrefined", file=sys.stderr)
        else:
            vol, field, info["refine"] = refine_field(
                trainer, field, vol, averaged_field(trainer, kept, share), decider, progress)
            info["refine"].update(decided_by)
            parts.add("refined_grid", info["refine"].pop("grid", None))
            if cfg.refine_output == "voxels":
                info["export"] = {"stem": EXPORT_STEMS["voxels"], "is_result": False}
    # vol is the exported field's voxelisation whenever the export is the result
    parts.add("export", vol if info["export"]["is_result"] else None)
    info["parts"] = parts.record
    info["seconds"] = time.perf_counter() - t0
    return vol, field, info


def field_volume(trainer, g: Gaussians) -> np.ndarray:
    """Plain Gaussians voxelised on the run's grid at its extent, [x, y, z] float32."""
    from mi_grg.core.voxelizer import voxelize
    return voxelize(g, trainer.case.geometry, extent=trainer.extent)


def projections(trainer, g: Gaussians, views) -> np.ndarray:
    """Exact line integrals [view, v, u] of plain Gaussians for view indices ``views``."""
    import drjit as dr
    geo = trainer.case.geometry
    nv, nu = geo.nDetector
    out = np.empty((len(views), nv, nu), np.float32)
    with dr.suspend_grad():
        for i in range(0, len(views), VIEW_CHUNK):
            v = np.asarray(views[i:i + VIEW_CHUNK])
            img = trainer._project(g, geo.angles[v], None)
            out[i:i + len(v)] = np.asarray(img.numpy(), np.float32).reshape(len(v), nv, nu)
    return out


def anchored_data(trainer, g: Gaussians, vol: np.ndarray, views) -> np.ndarray:
    """b' = b - (P(G) - A V(G)) on ``views`` (module docstring, step 2)."""
    from mi_grg.core.joseph import forward_project
    geo = trainer.case.geometry
    views = np.asarray(views)
    joseph = forward_project(vol, geo, geo.angles[views])
    return trainer.case.train[views] - (projections(trainer, g, views) - joseph)


def decide_length(trainer, kept: Gaussians, progress: bool = True,
                  anchored: bool = True, start=None, patience: int | None = None,
                  norm_A: float | None = None) -> dict:
    """The refinement's length from the kept field (module docstring, step 2): PDHG on the
    fitted views' anchored data (``anchored``, else the measured data), the held-out
    residual every ``CHECK_EVERY`` iterations, from ``start`` (the kept field's
    ``field_volume``; None: made here). The length is the first check at which the
    residual has made the share ``refine_fall`` of its fall from the start to the curve's
    minimum (1: the minimum), or is within the share ``refine_tol`` of that minimum,
    whichever comes first. The curve stops ``patience`` checks after its last new
    minimum (None: ``PATIENCE``; 0: at the cap). ``norm_A``: the fitted views' ||A|| from
    an earlier decision (None: PDHG's power iteration).
    Returns {"iterations", "at_cap", "curve": [(iteration, held-out MSE)], "heldout_mse"
    (the curve's minimum), "heldout_mse_chosen" (at "iterations"), "heldout_tiles" (the
    minimum's ``tile_means``), "norm_A", "seconds"}."""
    from mi_grg.classical.pdhg import PDHG
    from mi_grg.core.joseph import forward_project
    from tqdm import tqdm
    cfg, geo = trainer.cfg.protocol, trainer.case.geometry
    t0 = time.perf_counter()
    held = np.asarray(trainer.held_idx)
    fit = np.setdiff1d(np.arange(geo.n_views), held)
    if start is None:
        start = field_volume(trainer, kept)
    if anchored:
        b_fit = anchored_data(trainer, kept, start, fit)
        b_held = anchored_data(trainer, kept, start, held)
    else:
        b_fit, b_held = trainer.case.train[fit], trainer.case.train[held]

    def held_mse(x):
        r2 = np.square(forward_project(x, geo, geo.angles[held]) - b_held, dtype=np.float64)
        return float(np.mean(r2)), tile_means(r2)

    solver = PDHG(b_fit, geo, geo.angles[fit], lam=cfg.refine_lam, init=start,
                  norm_A=norm_A)
    cap = int(cfg.refine_max_iterations)
    patience = PATIENCE if patience is None else int(patience)
    best_mse, best_tiles = held_mse(start)
    curve = [(0, best_mse)]
    desc = f"refine: its length ({'anchored' if anchored else 'plain'})"
    with tqdm(total=cap, desc=desc, disable=not progress, leave=False) as bar:
        for it in range(1, cap + 1):
            solver.step()
            bar.update(1)
            if it % CHECK_EVERY == 0 or it == cap:
                x = np.asarray(solver.x.numpy(), np.float32).reshape(geo.nVoxel)
                mse, tiles = held_mse(x)
                if mse < best_mse:
                    best_mse, best_tiles = mse, tiles
                curve.append((it, mse))
                if past_patience(curve, patience):
                    break
    length, chosen = curve_length(curve, cfg.refine_fall, cfg.refine_tol)
    return {"iterations": length, "at_cap": length == cap, "curve": curve,
            "heldout_mse": best_mse, "heldout_mse_chosen": chosen,
            "heldout_tiles": best_tiles,
            "norm_A": solver.norm_A, "seconds": time.perf_counter() - t0}


def tile_means(r2: np.ndarray) -> np.ndarray:
    """Means of ``r2`` [view, v, u] over ``TILES`` x ``TILES`` detector tiles of each view
    (fewer on a detector with fewer pixels), flattened [view * tiles] float64: the units
    whose scatter gives a held-out comparison its standard error (neighbouring pixels
    share their errors; tiles far apart hardly do)."""
    nv, nu = r2.shape[1:]
    tv, tu = min(TILES, nv), min(TILES, nu)     # a tile holds at least one pixel
    rows = np.searchsorted((np.arange(nv) * tv) // nv, np.arange(tv))
    cols = np.searchsorted((np.arange(nu) * tu) // nu, np.arange(tu))
    sums = np.add.reduceat(np.add.reduceat(r2, rows, axis=1), cols, axis=2)
    counts = np.outer(np.diff(np.append(rows, nv)), np.diff(np.append(cols, nu)))
    return (sums / counts).reshape(-1)


def difference_z(a: np.ndarray, b: np.ndarray) -> float:
    """mean(a - b) over its standard error, for paired tile means ``a``, ``b`` (0 where
    they are equal; +-inf where they differ by a constant)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    se = float(np.std(d, ddof=1)) / np.sqrt(d.size) if d.size > 1 else 0.0
    m = float(np.mean(d))
    return m / se if se > 0 else (0.0 if m == 0 else float(np.sign(m)) * np.inf)


def curve_length(curve, fall: float, tol: float) -> tuple:
    """(iteration, held-out MSE) of the first check of ``curve`` [(iteration, held-out
    MSE, ...)] that has made the share ``fall`` of the fall from its start to its minimum,
    or is within the share ``tol`` of that minimum, whichever comes first."""
    start, best = curve[0][1], min(c[1] for c in curve)
    # the residual's tail flattens while the grid takes on voxel-scale detail that no
    # view checks: stopping once most of the fall is made avoids it
    # (never below the minimum: rounding in the difference must not skip it)
    target = max(start - float(fall) * (start - best), best, (1.0 + float(tol)) * best)
    return next((c[0], c[1]) for c in curve if c[1] <= target)


def past_patience(curve: list, patience: int) -> bool:
    """Whether a length decision's curve [(iteration, held-out MSE)] has run ``patience``
    checks past its (first) minimum (0: never)."""
    best = min(range(len(curve)), key=lambda i: curve[i][1])
    return bool(patience) and len(curve) - 1 - best >= patience


def refine_field(trainer, field: Gaussians, vol: np.ndarray, kept: Gaussians, decider,
                 progress: bool = True) -> tuple:
    """(vol_pred, exported Gaussians, info) of steps 2-3 for the returned ``field`` (plain,
    voxel-averaged) with voxelisation ``vol``; ``kept`` decides the length on the held-out
    views of ``decider`` (the trainer itself, or its decision run)."""
    from mi_grg.training.distill import fit_to_volume
    cfg = trainer.cfg.protocol
    forms = {"auto": (True, False), "on": (True,), "off": (False,)}[cfg.refine_anchor]
    resolved = None
    if cfg.refine_anchor == "auto":
        from mi_grg.training.densify import demand
        resolved = demand(trainer.state.log, trainer.densifier.window)
        if not resolved["met"]:     # the field's sub-voxel content is not the object's
            forms = (False,)
    start = field_volume(decider, kept)     # once for both forms
    lengths, norm_A = {}, None
    for a in forms:     # both forms run on the same views: one power iteration serves
        lengths[a] = decide_length(decider, kept, progress, anchored=a, start=start,
                                   norm_A=norm_A)
        norm_A = lengths[a]["norm_A"]
    # ties keep the anchor (listed first)
    anchored = min(forms, key=lambda a: lengths[a]["heldout_mse"])
    length = lengths[anchored]
    info = {"lam": cfg.refine_lam, "iterations": length["iterations"],
            "at_cap": length["at_cap"], "cap": cfg.refine_max_iterations,
            "patience": PATIENCE,
            "heldout_mse": {"start": length["curve"][0][1],
                            "refined": length["heldout_mse_chosen"],
                            "minimum": length["heldout_mse"]},
            "fall": cfg.refine_fall, "tol": cfg.refine_tol,
            "curve": length["curve"],
            "decision_seconds": sum(x["seconds"] for x in lengths.values()),
            "anchor": {"rule": cfg.refine_anchor, "anchored": anchored,
                       "densification": resolved,
                       "heldout_mse": {("anchored" if a else "plain"): x["heldout_mse"]
                                       for a, x in lengths.items()},
                       # the anchor's advantage in standard errors of the tiles' paired
                       # differences (negative: anchored lower)
                       "z": (difference_z(lengths[True]["heldout_tiles"],
                                          lengths[False]["heldout_tiles"])
                             if len(forms) == 2 else None),
                       # every form's held-out curve, so that a length rule can be
                       # replayed on both
                       "curves": {("anchored" if a else "plain"): x["curve"]
                                  for a, x in lengths.items()}}}
    if length["at_cap"]:
        print(f"refine=tv: the held-out residual still fell at refine_max_iterations="
              f"{cfg.refine_max_iterations} (metrics.json: at_cap); a 4x higher cap measured "
              "no better in 3-D PSNR (docs/benchmarks.md, \"The refinement's cap\")",
              file=sys.stderr)
    if length["iterations"] == 0:
        return vol, field, {**info, "grid": vol}
    t0 = time.perf_counter()
    grid = final_grid(trainer, field, vol, anchored, length["iterations"])
    info["final_seconds"] = time.perf_counter() - t0
    info["grid"] = grid
    if cfg.refine_output == "voxels":
        return grid, field, info
    t0 = time.perf_counter()
    fitted, fit = fit_to_volume(field, trainer.case.geometry, grid, lr=_fit_rates(trainer),
                                iterations=trainer.cfg.protocol.fit_iterations,
                                extent=trainer.extent, progress=progress)
    info["fit"] = {**fit, "seconds": time.perf_counter() - t0}
    return field_volume(trainer, fitted), fitted, info


def final_grid(trainer, field: Gaussians, vol: np.ndarray, anchored: bool,
               iterations: int) -> np.ndarray:
    """The refined grid [x, y, z] (step 2): ``iterations`` of PDHG at ``refine_lam`` from
    ``vol`` (the field's voxelisation) on every view's anchored data (``anchored``) or
    measured data."""
    from mi_grg.classical.pdhg import pdhg
    geo = trainer.case.geometry
    data = (anchored_data(trainer, field, vol, np.arange(geo.n_views)) if anchored
            else trainer.case.train)
    return pdhg(data, geo, n_iter=iterations, lam=trainer.cfg.protocol.refine_lam,
                init=vol, progress=False)


def kept_field(trainer, progress: bool = True, decision: bool = True) -> tuple:
    """(the kept field, plain, or None; a record; the trainer whose held-out views judge
    it): the state kept before the held-out views joined training, or without held-out
    views the decision run's (``decision``; else None)."""
    st = trainer.state
    if len(trainer.held_idx) == 0:
        if not decision:
            return None, {"skipped": "no held-out views (holdout_every=0)"}, None
        run, record = decision_run(trainer, progress)
        if run is None:
            return None, record, None
        kept = run.field_gaussians(run.state.kept_raw, run.state.kept_density_scale)
        return kept, {"decision_run": record}, run
    if st.kept_raw is None:
        return None, {"skipped": "no state kept before the held-out views joined"}, None
    return trainer.field_gaussians(st.kept_raw, st.kept_density_scale), {}, trainer


def field_share(trainer, kept: Gaussians | None = None, decider=None) -> tuple:
    """(the share of a voxel's box variance the result blurs the field by, record): the
    configured ``voxel_average``, plus under ``field_blur="heldout"`` the share of
    ``BLUR_SHARES`` whose blur alone of ``kept`` (the plain kept field; None: the
    trainer's own) has the lowest residual on ``decider``'s held-out views (module
    docstring, step 1).
    Without a kept state or held-out views nothing is added, and the record says why."""
    cfg = trainer.cfg.protocol
    base = float(cfg.voxel_average)
    record = {"rule": cfg.field_blur, "voxel_average": base, "added": 0.0, "share": base}
    if cfg.field_blur == "none":
        return base, record
    if kept is None:
        kept, why, decider = kept_field(trainer, decision=False)
        if kept is None:
            return base, {**record, "skipped": why["skipped"]}
    held = np.asarray(decider.held_idx)
    measured = decider.case.train[held].astype(np.float64)
    mse = []
    for extra in BLUR_SHARES:
        # the views judge the field against the continuous object: the voxel's own
        # share is not theirs to judge, so the blur they choose adds to it
        r = projections(decider, averaged_field(decider, kept, extra), held) - measured
        mse.append(float(np.mean(np.square(r))))
    added = BLUR_SHARES[int(np.argmin(mse))]
    return base + added, {**record, "added": added, "share": base + added,
                          "heldout_mse": dict(zip(map(str, BLUR_SHARES), mse))}


def decision_run(trainer, progress: bool = True) -> tuple:
    """(the decision run's finished ``Trainer`` or None, record) for a run without held-out
    views: the same configuration with the stop rule's split, whose kept state decides the
    refinement's length; None with the reason in ``record["skipped"]`` when none can be
    made (a time_budget, too few views for the split, no kept state)."""
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
    return run, {"holdout_every": every, "seconds": time.perf_counter() - t0,
                 "kept_iteration": summary["kept_iteration"],
                 "held_out_views": run.held_idx.tolist()}


def averaged_field(trainer, g: Gaussians, share: float | None = None) -> Gaussians:
    """``g`` blurred by ``share`` of a voxel's box variance (None: ``field_share``'s): the
    result's step 1, for the studies and benches that replay parts of ``finish``."""
    from mi_grg.core.voxel_average import convolve_gaussians, voxel_variance
    if share is None:
        share = field_share(trainer)[0]
    if share <= 0:
        return g
    return convolve_gaussians(g, share * voxel_variance(trainer.case.geometry, 1.0))


def _fit_rates(trainer) -> dict:
    """The fit back's Adam rates: the training's initial rates x ``fit_rate_scale``."""
    o, f = trainer.cfg.optim, trainer.cfg.protocol.fit_rate_scale
    return {"positions": f * o.lr_position, "raw_densities": f * o.lr_density,
            "raw_scales": f * o.lr_scale, "raw_rotations": f * o.lr_rotation}


class _Parts:
    """Research record: each step's 3-D PSNR against the ground truth (None without one)."""

    def __init__(self, trainer):
        self.gt = getattr(trainer.case, "vol_gt", None)
        self.record = {}

    def add(self, name: str, vol) -> None:
        """``vol``: a volume, a function that makes one (made only with a ground truth),
        or None."""
        if self.gt is None or vol is None:
            self.record[name] = None
            return
        from mi_grg.evaluation.metrics import psnr_3d
        self.record[name] = float(psnr_3d(vol() if callable(vol) else vol, self.gt))
