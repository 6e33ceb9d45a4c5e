"""GR-Gaussian / R2-Gaussian training: the loop that ties the components together.

    FDK of the fitting views -> De-Init (or plain FDK init for R2) -> per iteration: one
    view's projection loss (L1 or RMS + lambda_ssim D-SSIM) + lambda_tv TV on a random voxelised
    block (every ``tv_every``-th iteration, weighted ``tv_every`` x) + lambda_lap graph
    Laplacian -> Adam -> PGA densification every ``densify_interval`` iterations inside
    its window (the paper's 100 of 30k, scaled to the run: 25 up to 7500 iterations; graph
    rebuilt after each) -> held-out-view PSNR every ``eval_every`` iterations ->
    early stop, keeping the latest state within the stop margin of the best (or the best:
    ``keep_state``) -> once the stop rule is done, every view trains to the end
    (``mi_grg.protocol.views``).

The iteration count comes from ``iteration_rule`` (or ``iterations``), or is planned to a
wall-clock ``time_budget`` (``mi_grg.training.budget``); the schedule scales with it up to
the ``horizon`` (the rule's count unless set): a longer run follows the horizon's schedule
and then trains every view at a learning rate that keeps decaying, so that more iterations
converge instead of stretching the fast early phase (docs/benchmarks.md, "More
iterations").

Every component is switched by ``TrainConfig`` (``mi_grg.training.config``), so one loop runs
R2-Gaussian (``--method r2``), GR-Gaussian (``--method gr``) and every ablation between.
Runs write checkpoints that ``resume=True`` continues from: a crashed run loses at most
``checkpoint_interval`` iterations, an interrupted one (Ctrl-C) none: the iteration in
progress finishes and a checkpoint is written before the KeyboardInterrupt.

Units: the loop works in the case's units (R2-Gaussian's normalised scene, volume in
[-1, 1]^3, when the case was loaded with rescaling); densities are never rescaled.
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.data.case import Case
from mi_grg.training.checkpoint import TrainState, checkpoint_time_plan, load_checkpoint
from mi_grg.training.config import ITERATION_RULE, TRAIN_EXTENT, TrainConfig, make_config
from mi_grg.training.interrupt import DeferredInterrupt
from mi_grg.training.stopping import StopControl
from mi_grg.training.schedule import (_scaled, checkpoint_interval,  # noqa: F401
                                      gaussian_cap, iteration_rule)
from mi_grg.classical.pdhg import reconstruct_pdhg
from mi_grg.core.fdk import fdk
from mi_grg.protocol.views import ViewProtocol
from mi_grg.training.run_budget import TimeBudget
from mi_grg.training.run_files import RunFiles
from mi_grg.training.step import (REFERENCE_N, StepConfig, StepInputs,  # noqa: F401
                                  evaluate_gradients, laplacian_weight, loss_and_grads,
                                  view_arrays)

def carry_density_scale(raw: dict, old_scale, new_scale, source) -> dict:
    """Densities x old_scale[source] / new_scale, after a densification and graph rebuild.

    The graph field renders kernel j with density rho_j (1 + sum_i w_ij), and the sum
    changes whenever the graph is rebuilt: a clone and its copy sit at distance 0 (w = 1 to
    each other), so the pair would render about 1 / (1 + sum w) ~ 25 % more mass than its
    parent although the clone halved the density to conserve it. Rescaled, every kernel
    renders with its source row's old multiplier, so densification changes the field
    exactly as R2-Gaussian's rules change the plain field (``rebuild_keeps_field``).

    raw: densified raw parameters [N_after]; old_scale: mi.Float [N_before] (multiplier of
    the old graph); new_scale: mi.Float [N_after] (of the rebuilt graph, >= 1);
    source: mi.UInt32 [N_after] (``PGADensifier`` info["source"]). Returns a new raw dict
    (only raw_densities changes), gradients enabled."""
    g = Gaussians.from_raw({k: dr.detach(v) for k, v in raw.items()})
    ratio = dr.gather(mi.Float, old_scale, source) / dr.maximum(new_scale, 1.0)
    out = dict(raw)
    out["raw_densities"] = g.replace(densities=g.densities * ratio).to_raw()["raw_densities"]
    dr.enable_grad(out["raw_densities"])
    dr.eval(out["raw_densities"])
    return out


# ---------------------------------------------------------------------------- training
class Trainer:
    """One training run on a case. Construct, then ``run()``; see the module docstring."""

    def __init__(self, case: Case, cfg: TrainConfig, out_dir=None, progress: bool = True,
                 resume=False):
        t_begin = time.perf_counter()
        self.case, self.cfg, self.progress = case, cfg, progress
        self.files = RunFiles(out_dir)
        self.out, self.checkpoint_path = self.files.out, self.files.checkpoint_path
        geo = case.geometry
        # resume: True continues from out_dir's checkpoint; a path from that file (a run
        # written into a new folder that replaces its old output when done: the CLI's)
        source = (Path(resume) if isinstance(resume, (str, os.PathLike))
                  else self.checkpoint_path if resume else None)
        resuming = source is not None and source.exists()
        # time_budget: planned after De-Init (mi_grg.training.budget); a resumed run
        # continues its recorded plan. Until then the rule's count stands in.
        plan = None
        if resuming and cfg.run.time_budget is not None:
            plan = checkpoint_time_plan(source)
            if plan is None:
                raise ValueError(f"checkpoint {source} has no time plan to "
                                 "resume with time_budget")
        self._schedule(cfg.schedule.iterations if cfg.schedule.iterations is not None else
                       plan["iterations"] if plan else iteration_rule(geo))
        self.fit_idx, self.held_idx = self.views.fit, self.views.held
        self.targets = [mi.TensorXf(np.ascontiguousarray(case.train[i], np.float32))
                        for i in range(geo.n_views)]
        self.uses_graph = (cfg.graph.use_graph_field or cfg.densify.use_pga
                           or cfg.graph.lambda_lap > 0)
        self.extent = cfg.schedule.extent if cfg.schedule.extent is not None else TRAIN_EXTENT
        # The TV term is a regulariser on a random block, not a measurement: a shorter
        # support costs a third of the voxel pairs (its field differs from the full one by
        # at most rho exp(-9/2) = 0.011 rho per Gaussian).
        self.tv_extent = cfg.losses.tv_extent if cfg.losses.tv_extent is not None else self.extent
        if cfg.protocol.monitor_3d and case.vol_gt is None:
            raise ValueError("monitor_3d stops on the 3-D PSNR against a ground truth, and "
                             "this case has none (vol_gt.npy); use the held-out views")
        self.stopping = StopControl(cfg.protocol)
        self.graph = None
        # The graph field's multiplier 1 + sum w of the current graph (None: plain field),
        # set with the graph: constant until the next rebuild.
        self._density_scale = None
        # Density multiplier (graph field) that went with the returned state.
        self.final_density_scale = None
        self.step_cfg = StepConfig.from_train_config(cfg, geo, self.extent, self.tv_extent)
        self._view_arrays = {}
        self.recording = None
        if cfg.run.frozen_step:
            from mi_grg.training.recording import Recording
            self.recording = Recording(self.step_cfg)
        if resuming:
            self.state = load_checkpoint(source, self.optimizer, self.densifier,
                                         self.stopper, cfg)
            self.init_info = {"resumed_from": self.state.iteration}
        else:
            if source is not None:
                print(f"no checkpoint at {source}; starting from scratch")
            g, self.init_info = self._initial_gaussians()
            self.state = TrainState(iteration=0, raw=g.to_raw(),
                                    rng=np.random.default_rng(
                                        cfg.schedule.seed).bit_generator.state)
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = self.state.rng
        # Wall clock of the calls this run resumed from (metrics.json's seconds add it).
        self.resumed_seconds = self.state.wall_seconds if resuming else 0.0
        self._wall_start = t_begin - self.resumed_seconds
        self.budget = None
        if cfg.run.time_budget is not None:
            self.budget = TimeBudget(self)
            self.budget.start(resuming, None if resuming else g, t_begin)

    @property
    def stopper(self):
        """The run's EarlyStopper (``StopControl``)."""
        return self.stopping.stopper

    @property
    def _stop(self):
        """Where the stop rule fired (views.Stop), or None."""
        return self.stopping.stop

    @property
    def time_plan(self) -> dict | None:
        """The run's time plan (time_budget runs; None otherwise), kept in its state so that
        checkpoints carry it."""
        return self.state.time_plan

    def _schedule(self, iterations: int) -> None:
        """The parts that depend on the run's length: the scaled schedule, the view protocol,
        a fresh densifier and optimiser."""
        from mi_grg.training.densify import DensifyWindow, PGADensifier
        from mi_grg.training.optim import Adam
        cfg, geo = self.cfg, self.case.geometry
        self.iterations = int(iterations)
        self.horizon = (cfg.schedule.horizon if cfg.schedule.horizon is not None
                        else iteration_rule(geo))
        # The config's schedule is the paper's, for 30k iterations: scale it to this run's
        # (or, for a longer run, to the horizon's).
        self.sched = sched = _scaled(cfg, self._scheduled(self.iterations))
        # Views: held out while the stop rule decides, then trained, so that every view
        # counts (docs/benchmarks.md, "Every view counts"); the research rule monitor_3d
        # judges the ground truth, so there the views stay held out.
        self.views = ViewProtocol(geo.n_views, cfg.protocol.holdout_every,
                                  1.0 if cfg.protocol.monitor_3d else cfg.protocol.holdout_until,
                                  self.iterations, sched["eval_every"],
                                  cfg.protocol.holdout_catch_up, horizon=self.horizon)
        # The config's window and cap are the paper's; this run's depend on its length and
        # grid: the densifier's window (its state), the settings stay as written.
        window = DensifyWindow(start=sched["densify_start"], stop=sched["densify_stop"],
                               interval=sched["densify_interval"],
                               max_count=gaussian_cap(cfg, geo))
        self.densifier = PGADensifier(cfg.densify, seed=cfg.schedule.seed, window=window)
        self.optimizer = Adam.from_train_config(cfg, max_steps=self._scheduled(self.iterations),
                                                anneal=True)

    def _scheduled(self, iterations: int) -> int:
        """The length the schedule is scaled to: the run's, at most the horizon."""
        return min(int(iterations), self.horizon)

    def _psnr_3d(self, raw: dict) -> float:
        """The research log's 3-D PSNR of the current state against the ground truth."""
        from mi_grg.evaluation.metrics import psnr_3d
        return float(psnr_3d(self.volume(raw, self._density_scale), self.case.vol_gt))

    # ------------------------------------------------------------------ pieces
    def _initial_gaussians(self):
        from mi_grg.training.init import init_gaussians, sigma_d_voxels
        geo, cfg = self.case.geometry, self.cfg
        fit_geo = geo.with_angles(geo.angles[self.fit_idx])
        info = {"volume": cfg.deinit.init}
        if cfg.deinit.init == "pdhg":
            # the fitted views only: the held-out ones still decide this run's stop
            fitted = Case(geometry=fit_geo, train=self.case.train[self.fit_idx])
            vol, decided = reconstruct_pdhg(fitted, oracle=False, progress=False)
            info["pdhg"] = {"chosen": decided["chosen"], "search": decided.get("search"),
                            "seconds": decided["decision_seconds"] + decided["final_seconds"]}
        else:
            vol = fdk(self.case.train[self.fit_idx], fit_geo)
        # The signed FDK is filtered: clipping first would lift the air's zero-mean noise to
        # a positive mean, and after the filter every voxel of the cube would pass tau.
        sigma = sigma_d_voxels(cfg.deinit.sigma_d, geo.nVoxel, cfg.deinit.sigma_d_grid)
        info["sigma_d_voxels"] = sigma
        g = init_gaussians(vol, geo, n_points=cfg.deinit.n_points, tau=cfg.deinit.init_tau,
                           sigma_d=sigma or None, density_rescale=cfg.deinit.density_rescale,
                           seed=cfg.schedule.seed, info=info)
        if cfg.graph.use_graph_field:
            # The graph-augmented field multiplies each kernel's density by 1 + sum_i w_ij
            # (about 1 + k/2 e^-1 .. 1 + k); the init densities were calibrated for the plain
            # field, so divide by that factor: the initial field is the same either way.
            from mi_grg.training.graph import build_graph, graph_density_scale
            scale = graph_density_scale(build_graph(g.positions, k=cfg.graph.k,
                                                    s=cfg.graph.graph_s))
            g = g.replace(densities=g.densities / scale)
            info["graph_field_init_divisor_mean"] = float(dr.mean(scale)[0]
                                                          if dr.width(dr.mean(scale)) else 1.0)
        return g, info

    def _rebuild_graph(self, positions):
        """Graph of ``positions`` (the state remembers them, so a resumed run rebuilds the
        very same graph rather than one of later positions)."""
        from mi_grg.training.graph import build_graph, graph_density_scale
        self._density_scale = None
        if not self.uses_graph:
            self.graph = None
            return
        p = mi.Point3f(dr.detach(positions))
        self.graph = build_graph(p, k=self.cfg.graph.k, s=self.cfg.graph.graph_s)
        self.state.graph_positions = np.stack([np.asarray(c) for c in p], -1)
        if self.cfg.graph.use_graph_field:
            # constant until the next rebuild: computed once here, not every iteration
            self._density_scale = graph_density_scale(self.graph)
            dr.eval(self._density_scale)

    def _project(self, g, angles, density_scale, means2d=None):
        from mi_grg.core.projector import project_dr
        return project_dr(g, self.case.geometry, angles=angles, extent=self.extent,
                          density_scale=density_scale, means2d=means2d)

    def volume(self, raw=None, density_scale=None) -> np.ndarray:
        """The reconstruction [x, y, z]: the Gaussian field voxelised at voxel centres.

        Without arguments: the returned state with the graph-field density scale it was
        trained with (so the volume is the field that was fitted to the projections).
        """
        from mi_grg.core.voxelizer import voxelize
        if raw is None:
            raw, density_scale = self.state.raw, self.final_density_scale
        g, density_scale = self._field(raw, density_scale)
        return voxelize(g, self.case.geometry, extent=self.extent, density_scale=density_scale)

    def field_gaussians(self, raw=None, density_scale=None) -> Gaussians:
        """A state (default: the returned one) as plain Gaussians whose sum is its volume:
        with the graph field, each density times its multiplier 1 + sum_i w_ij, so that
        they render ``volume()`` without the graph."""
        if raw is None:
            raw, density_scale = self.state.raw, self.final_density_scale
        g, scale = self._field(raw, density_scale)
        return g if scale is None else g.replace(densities=g.densities * scale)

    def _field(self, raw, density_scale):
        """(Gaussians of ``raw``, their graph-field multiplier or None): ``density_scale`` if
        given, else, with the graph field on, the one of a graph built on these positions."""
        g = Gaussians.from_raw({k: dr.detach(v) for k, v in raw.items()})
        if density_scale is None and self.cfg.graph.use_graph_field:
            from mi_grg.training.graph import build_graph, graph_density_scale
            density_scale = graph_density_scale(build_graph(g.positions, k=self.cfg.graph.k,
                                                            s=self.cfg.graph.graph_s))
        return g, density_scale

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict:
        """Train to the end of the budget or an early stop; returns the run's summary and
        (with an output folder) writes the checkpoint, log, plot and Gaussians."""
        from tqdm import tqdm
        st = self.state
        raw = {k: dr.detach(v) for k, v in st.raw.items()}
        for v in raw.values():
            dr.enable_grad(v)
        gp = st.graph_positions
        self._rebuild_graph(raw["positions"] if gp is None else
                            mi.Point3f(*[mi.Float(np.ascontiguousarray(gp[:, i])) for i in range(3)]))
        # Wall clock of the training alone: research logging (3-D PSNR) is subtracted.
        self._t_start = time.perf_counter() - st.seconds
        bar = tqdm(total=self.iterations, initial=st.iteration, disable=not self.progress,
                   desc=f"train ({'graph' if self.uses_graph else 'no graph'})",
                   dynamic_ncols=True, mininterval=1.0)
        last_psnr = None
        # The stop rule's verdict (restored on resume) decides the view sets and the end.
        self.stopping.restore()
        with DeferredInterrupt() as interrupt:
            while st.iteration < self.views.end(self._stop) and st.stopped_by is None:
                it = st.iteration + 1
                raw, loss_value = self._step(it, raw)
                densified = self.densifier.is_densify_iteration(it)
                if densified:
                    raw = self._densify_and_rebuild(it, raw)
                st.iteration, st.raw = it, raw
                row = {"iteration": it,
                       "seconds": round(time.perf_counter() - self._t_start, 3),
                       "loss": loss_value, "n_gaussians": dr.width(raw["raw_densities"])}
                if self.budget is not None and self.budget.after_iteration(
                        it, densified, row["seconds"], row["n_gaussians"]):
                    bar.total = self.iterations
                raw = self._evaluate(it, raw, row)
                last_psnr = row.get("heldout_psnr", last_psnr)
                st.log.append(row)
                bar.update(1)
                bar.set_postfix(loss=f"{loss_value:.4f}", N=row["n_gaussians"],
                                heldout=f"{last_psnr:.2f}" if last_psnr is not None else "-",
                                refresh=False)
                st.seconds = time.perf_counter() - self._t_start
                st.rng = self.rng.bit_generator.state
                if (self.budget is not None and st.stopped_by is None
                        and self.budget.out_of_time(st.seconds)):
                    st.stopped_by = (f"time budget ({self.cfg.run.time_budget:g} s) reached at "
                                     f"iteration {it} of {self.iterations} planned")
                every = checkpoint_interval(self.cfg.run.checkpoint_every, self.iterations)
                if it % every == 0 or st.stopped_by is not None or interrupt.requested:
                    self._save_checkpoint()
                if interrupt.requested:
                    bar.close()
                    raise KeyboardInterrupt
        bar.close()
        return self._finish()

    def _step(self, it: int, raw: dict):
        """One iteration: draw a training view (``views.train_views``), then the TV block's
        corner; the loss and its gradients (``step.loss_and_grads``, replayed from a
        recording where one serves); densification statistics; Adam. Returns (new raw,
        loss value)."""
        view = int(self.rng.choice(self.views.train_views(it, self._stop),
                                   p=self.views.draw_weights(it, self._stop)))
        inputs = self._step_inputs(raw, view, self._tv_start(it))
        done = self._replay(inputs) if self.recording is not None else None
        if done is None:        # traced (or handed back by the recording)
            out = loss_and_grads(self.step_cfg, inputs)
            done = {"grads": out.grads, "gnorm": out.gnorm}, float(out.loss[0])
        out, loss_value = done
        if not math.isfinite(loss_value):
            raise FloatingPointError(f"loss is {loss_value} at iteration {it}")
        if "stats" in out:      # the statistics and Adam were recorded too
            self.densifier.add(out["stats"])
            return self.optimizer.apply(out["raw"], out["m"], out["v"]), loss_value
        self.densifier.accumulate(out["gnorm"], visible=out["gnorm"] > 0)
        return self.optimizer.step(raw, grads=out["grads"]), loss_value

    def _step_inputs(self, raw: dict, view: int, start=None, density_scale="current"):
        """The step's inputs of this state for ``view`` (TV block at ``start``)."""
        lap = None
        if self.step_cfg.lambda_lap > 0 and self.graph is not None:
            lap = laplacian_weight(self.step_cfg.lambda_lap, dr.width(raw["raw_densities"]))
        arrays = self._view_arrays.get(view)
        if arrays is None:
            arrays = self._view_arrays[view] = view_arrays(self.case.geometry, view,
                                                           self.step_cfg.shared)
        ds = self._density_scale if density_scale == "current" else density_scale
        return StepInputs(raw, arrays, self.targets[view], ds, self.graph, lap, start)

    def _replay(self, inputs: StepInputs):
        """(outputs, loss value) of the recorded step, with the statistics and Adam
        recorded too where they can be; None: run this iteration traced."""
        n = dr.width(inputs.raw["raw_densities"])
        stats = self.densifier.recorded_inputs(n)
        adam = self.optimizer.recorded_inputs(inputs.raw)
        update = None if stats is None or adam is None else {"stats": stats, "adam": adam}
        return self.recording.step(inputs, update, (self.optimizer.betas, self.optimizer.eps))

    def _tv_start(self, it: int):
        """This iteration's TV block corner [x, y, z] (a random draw), or None (no TV)."""
        cfg = self.cfg
        if not (cfg.losses.lambda_tv > 0 and it % cfg.losses.tv_every == 0):
            return None
        nvox = np.asarray(self.case.geometry.nVoxel)
        block = self.step_cfg.tv.block
        return [int(self.rng.integers(0, int(nvox[a] - block[a]) + 1)) for a in range(3)]

    def _densify_and_rebuild(self, it: int, raw: dict) -> dict:
        """PGA densification (graph term from the current graph), then a new graph; with
        ``rebuild_keeps_field`` the densities carry the old graph's multiplier over."""
        from mi_grg.training.graph import mean_abs_density_difference
        cfg = self.cfg
        term = None
        if cfg.densify.use_pga and self.graph is not None:
            term = mean_abs_density_difference(self.graph,
                                               dr.detach(Gaussians.from_raw(raw).densities))
        old_scale = self._density_scale if cfg.graph.rebuild_keeps_field else None
        raw, info = self.densifier.step(it, raw, self.optimizer, graph_term=term,
                                        bbox=self.case.geometry.bbox())
        self._rebuild_graph(raw["positions"])
        if info["densified"] and old_scale is not None:
            raw = carry_density_scale(raw, old_scale, self._density_scale, info["source"])
        return raw

    def _evaluate(self, it: int, raw: dict, row: dict) -> dict:
        """Logging and early stopping at this iteration: the 3-D PSNR (research logging,
        when there is a ground truth and it is due) and, every ``eval_every`` iterations
        and at the last while the held-out views decide (``views.decides``), their PSNR,
        which the stopper judges once densification has ended (``monitor_3d``: the 3-D
        PSNR instead). Fills ``row`` (psnr_3d, heldout_psnr). On a stop: the state's
        ``stopped_by`` when the run ends here, else the kept state, from which training
        goes on on every view. Returns the state to continue from."""
        cfg, st = self.cfg, self.state
        is_eval = it % self.sched["eval_every"] == 0 or it == self.iterations
        want_3d = self.case.vol_gt is not None and (
            (it % cfg.protocol.log_3d_every == 0 if cfg.protocol.log_3d_every else is_eval)
            or (cfg.protocol.monitor_3d and is_eval))
        if want_3d:
            # Research logging: not counted in the training time, except against a time
            # budget, which is wall clock (mi_grg.training.budget prices it)
            t3 = time.perf_counter()
            row["psnr_3d"] = self._psnr_3d(raw)
            if cfg.run.time_budget is None:
                self._t_start += time.perf_counter() - t3
        # A held-out view is judged only while none of them has been trained on.
        if not is_eval or not (cfg.protocol.monitor_3d or self.views.decides(it, self._stop)):
            return raw
        row["heldout_psnr"] = self._heldout_psnr(raw)
        watched = row.get("psnr_3d") if cfg.protocol.monitor_3d else row["heldout_psnr"]
        raw, self._density_scale = self.stopping.judge(
            it, watched, it < self.sched["densify_stop"], st, raw, self._density_scale,
            self.views)
        return raw

    def _save_checkpoint(self) -> None:
        if self.checkpoint_path is not None:
            self.state.wall_seconds = time.perf_counter() - self._wall_start
            self.files.save_checkpoint(self.state, self.optimizer, self.densifier,
                                       self.stopper, self.cfg, max(self.case.geometry.nVoxel))

    def _finish(self) -> dict:
        """Why the run ended, the state to return (the last one once the held-out views
        have joined training; else the kept one, refitted on all views when
        ``refit_iterations``), the summary; with an output folder, the final checkpoint
        and train_log.csv / .png (the exported Gaussians are the result's,
        ``RunFiles.write_gaussians``)."""
        cfg, st, stop = self.cfg, self.state, self._stop
        self.stopping.ending(st, self.views, self.iterations)
        joined = self.views.joined(st.iteration, stop)
        returned = st.iteration
        if joined:      # the last state, trained on every view
            final, self.final_density_scale = st.raw, self._density_scale
        elif st.kept_raw is not None:
            final, self.final_density_scale = st.kept_raw, st.kept_density_scale
            returned = self.stopper.kept_iteration
        else:
            final, self.final_density_scale = st.raw, self._density_scale
        if (cfg.protocol.refit_iterations and st.kept_raw is not None
                and "budget" not in st.stopped_by and not joined):
            final = self._refit(final, cfg.protocol.refit_iterations)
        st.raw = final
        summary = {"iterations_run": st.iteration, "iterations_planned": self.iterations,
                   "stopped_by": st.stopped_by,
                   **self.stopping.summary(st, self.views, returned),
                   "n_gaussians": dr.width(final["raw_densities"]),
                   "train_seconds": st.seconds,
                   "schedule": {**self.sched, "horizon": self.horizon,
                                "scaled_to": self._scheduled(self.iterations)},
                   "checkpoint_every": checkpoint_interval(cfg.run.checkpoint_every,
                                                           self.iterations),
                   # wall clock of the earlier calls of a resumed run, to its checkpoint
                   # (0: not resumed); metrics.json's seconds include it
                   "resumed_seconds": self.resumed_seconds,
                   "max_gaussians": self.densifier.window.max_count,
                   "held_out_views": self.held_idx.tolist(), "init": self.init_info,
                   "time_plan": self.time_plan,
                   # what the automatic fields resolved to (lab.staleness.stale_keys compares)
                   "extent": self.extent, "iteration_rule": ITERATION_RULE}
        if self.out is not None:
            self._save_checkpoint()
            self.files.write_final(st.log, returned)
        return summary

    # ------------------------------------------------------------------ held-out views
    def _heldout_psnr(self, raw) -> float | None:
        """Mean PSNR of the held-out views' projections of ``raw`` (None without any)."""
        if len(self.held_idx) == 0:
            return None
        from mi_grg.evaluation.metrics import psnr_proj
        with dr.suspend_grad():
            g = Gaussians.from_raw(raw)
            img = self._project(g, self.case.geometry.angles[self.held_idx],
                                self._density_scale)
            pred = np.asarray(img.numpy())
        return float(psnr_proj(pred, self.case.train[self.held_idx]))

    def _refit(self, raw, n_iter: int):
        """Brief refit on all views (held-out ones included) after early stopping: the
        step's projection loss alone (``StepConfig.refit``)."""
        cfg = self.step_cfg.refit()
        raw = {k: dr.detach(v) for k, v in raw.items()}
        for v in raw.values():
            dr.enable_grad(v)
        for _ in range(n_iter):
            view = int(self.rng.integers(0, self.case.geometry.n_views))
            out = loss_and_grads(cfg, self._step_inputs(raw, view,
                                                        density_scale=self.final_density_scale))
            raw = self.optimizer.step(raw, grads=out.grads)
        return raw


# ---------------------------------------------------------------------------- methods
def _train_method(method: str):
    def run(case: Case, out_dir=None, config=None, resume=False,
            progress: bool = True, **overrides):
        cfg = make_config(method, config, **overrides)
        trainer = Trainer(case, cfg, out_dir=out_dir, progress=progress, resume=resume)
        summary = trainer.run()
        summary["config"] = cfg.to_flat()
        from mi_grg.training.result import finish
        vol, g, summary["result"] = finish(trainer, progress)
        if "refine" in summary["result"]:
            summary["refine"] = summary["result"].pop("refine")
        trainer.files.write_gaussians(g, summary["result"]["export"]["stem"])
        return vol, summary
    run.__name__ = f"reconstruct_{method}"
    run.__doc__ = (f"{method} training under the reconstruction contract: options are "
                   "TrainConfig fields (mi_grg.training.config), config (an XML file), resume "
                   "(True, or the checkpoint file to continue from), "
                   "progress, out_dir.")
    return run


reconstruct_gr = _train_method("gr")
reconstruct_r2 = _train_method("r2")
