"""Where one gr / r2 training iteration spends its time, on a late-training state.

    .venv/bin/python bench/train_step.py                      # 64^3 gr and r2, vs REFERENCE
    .venv/bin/python bench/train_step.py --sizes 64 128 --before 42a14d5
    .venv/bin/python bench/train_step.py --quick              # smoke run
    .venv/bin/python bench/train_step.py --variant cuda_ad_mono --before none   # on a GPU
    .venv/bin/python bench/train_step.py --frozen --methods gr        # frozen vs traced
    .venv/bin/python bench/train_step.py --frozen --methods gr --variant cuda_ad_mono

State: a seeded 64^3 (or 128^3) Shepp-Logan case, 25 noisy views of 1.5 n pixels
(bench/reconstruct.py's cells), trained with the method's defaults for ``--train-iters``
iterations (400 at 64^3: past the scaled densification window, ~80-120k Gaussians), saved
once to ``out/bench_cache/`` (not in git) with the raw parameters and the training views.
Every measurement starts from that state, so "before" and "after" time the same model.

Code compared: the working tree ("after") and ``--before REV`` ("before", default
``REFERENCE``, the code before issue 21's throughput work), whose ``mi_grg`` package is
exported with ``git archive`` into the cache and put first on PYTHONPATH. Each (code,
method, size) runs in its own process; ``--rounds`` alternates before/after processes
(ABAB...) so that both see the same machine load, and the table quotes the median over
rounds of each process's median.

One iteration mirrors ``Trainer.run``'s step (training.trainer): Gaussians.from_raw ->
project_dr of one random view (with means2d) -> L1 + D-SSIM -> TV on a random 32^3 block
every ``tv_every``-th iteration (weighted tv_every x) -> graph Laplacian -> backward ->
densification statistics + loss read -> Adam. Two timings per process:

* ``split``: a host synchronisation after each part, so each part's time is its own
  (projection forward, loss, TV forward, Laplacian forward, loss backward, projector
  backward, TV backward, Laplacian backward, statistics, Adam). TV parts are amortised
  over ``tv_every`` iterations.
* ``whole``: the step as the trainer runs it (no extra synchronisation), timed over pairs
  of iterations (one with TV, one without) / 2, with Dr.Jit's kernel history on: the sum
  of the kernels' execution times against the wall time gives the time spent outside
  kernels (Python tracing, kernel launches, host synchronisations, code-cache look-ups).

Densification (clone/split/prune + graph rebuild) runs only inside the scaled window; its
time is measured once per process on the state and amortised over the densification
interval (reported apart: late-training iterations do not pay it).

Equality check: each process also writes the loss and the gradients of every raw
parameter of one fixed iteration (view 3, fixed TV block); the harness reports the largest
difference between "before" and "after" relative to each gradient's largest entry.

Writes docs/bench/train_step.{md,json} (with os.getloadavg() before and after each process).

``--frozen``: the recorded step (``TrainConfig.frozen_step``, mi_grg.training.recording)
against the traced one, in one process per (method, size, round) on the same state: after
a warm-up (compilation, the recordings and their capacities), ``--blocks`` alternations of
``--iters`` traced pairs and ``--iters`` frozen pairs (iterations as Trainer.run composes
them, Adam included, kernel history on); per block the median wall time per iteration and
its time outside kernels, and per alternation the frozen / traced ratios; the table gives
the medians. Iterations the frozen step hands back to the traced path (a capacity
overflow) are counted. Equality: loss and gradients of one fixed iteration (view 3, fixed
TV block) by both paths. Writes docs/bench/train_step_frozen{,_cuda}.{md,json}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "out" / "bench_cache"
TRAIN_ITERS = {64: 400, 128: 600}
REFERENCE = "42a14d5"   # main before issue 21's throughput work: the "before" column
PARTS = ("setup", "proj_fwd", "loss_fwd", "tv_fwd", "lap_fwd", "loss_bwd", "proj_bwd",
         "tv_bwd", "lap_bwd", "stats_sync", "adam")
PART_TEXT = {"setup": "Gaussians.from_raw, means2d", "proj_fwd": "projection forward",
             "loss_fwd": "L1 + D-SSIM forward", "tv_fwd": "TV block voxelisation + TV, forward",
             "lap_fwd": "Laplacian forward", "loss_bwd": "L1 + D-SSIM backward",
             "proj_bwd": "projection backward (to raw parameters)",
             "tv_bwd": "TV block backward", "lap_bwd": "Laplacian backward",
             "stats_sync": "densification statistics + loss read (host sync)",
             "adam": "Adam step"}


# ====================================================================== the state
def _case(n: int):
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=n, det=int(1.5 * n), views=25)
    return simulate_case("shepp", geo, default_test_angles(25), NoiseModel(), seed=0)


def state_path(method: str, n: int) -> Path:
    return CACHE / f"train_state_{method}_{n}.npz"


def make_state(method: str, n: int, iters: int) -> None:
    """Train ``iters`` iterations with the method's defaults and save the raw state."""
    import mi_grg  # noqa: F401  (first: picks Dr.Jit's LLVM library and the variant)
    import numpy as np
    import drjit as dr
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    case = _case(n)
    cfg = make_config(method, None, iterations=iters)
    tr = Trainer(case, cfg, out_dir=None, progress=False)
    t0 = time.perf_counter()
    tr.run()
    raw = {k: dr.detach(v) for k, v in tr.state.raw.items()}
    arrays = {}
    for k, v in raw.items():
        arrays[k] = (np.asarray(v) if k == "raw_densities"
                     else np.stack([np.asarray(c) for c in v], -1))
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(state_path(method, n), train=np.asarray(case.train, np.float32),
             seconds=time.perf_counter() - t0, iterations=iters, **arrays)


# ====================================================================== worker
def _load_state(method: str, n: int):
    import numpy as np
    import drjit as dr
    import mitsuba as mi
    f = np.load(state_path(method, n))
    raw = {"positions": mi.Point3f(*[mi.Float(np.ascontiguousarray(f["positions"][:, i]))
                                     for i in range(3)]),
           "raw_scales": mi.Vector3f(*[mi.Float(np.ascontiguousarray(f["raw_scales"][:, i]))
                                       for i in range(3)]),
           "raw_rotations": mi.Vector4f(*[mi.Float(np.ascontiguousarray(f["raw_rotations"][:, i]))
                                          for i in range(4)]),
           "raw_densities": mi.Float(np.ascontiguousarray(f["raw_densities"]))}
    for v in raw.values():
        dr.enable_grad(v)
    return raw, np.asarray(f["train"])


def _train_extent():
    """The trainer's default extent where the code under test has one, else None (the
    projector's default: the code before 61ad6dd)."""
    try:
        from mi_grg.training.config import TRAIN_EXTENT
    except ImportError:
        return None
    return TRAIN_EXTENT


def _flat_options(config):
    """The config's fields by their flat names, whichever code is under test: ``to_flat``
    where TrainConfig is grouped into parts, its own flat fields before."""
    from types import SimpleNamespace
    flat = config.to_flat() if hasattr(config, "to_flat") else config.to_dict()
    return SimpleNamespace(**flat)


class _Step:
    """One training iteration, as Trainer.run composes it (see the module docstring)."""

    def __init__(self, method, n):
        import numpy as np
        import drjit as dr
        import mitsuba as mi
        from mi_grg.data.simulate import default_geometry
        from mi_grg.training.config import make_config
        from mi_grg.training.densify import PGADensifier
        from mi_grg.training.graph import build_graph, graph_density_scale
        from mi_grg.training.optim import Adam
        self.raw, train = _load_state(method, n)
        self.geo = default_geometry(n=n, det=int(1.5 * n), views=25)
        config = make_config(method, None)
        self.cfg = cfg = _flat_options(config)     # the options, read by their flat names
        from mi_grg.training.trainer import iteration_rule   # the code's own (Adam's decay)
        self.iterations = iteration_rule(self.geo)
        self.targets = [mi.TensorXf(np.ascontiguousarray(t)) for t in train]
        self.optimizer = Adam.from_train_config(config, max_steps=self.iterations)
        import mi_grg.training.densify as densify
        # a --before revision from before the one densification settings class has its own
        old = getattr(densify, "DensifyConfig", None)
        settings = old.from_train_config(config) if old is not None else config.densify
        self.densifier = PGADensifier(settings, seed=cfg.seed)
        self.uses_graph = cfg.use_graph_field or cfg.use_pga or cfg.lambda_lap > 0
        self.graph = self.ds = None
        if self.uses_graph:
            self.graph = build_graph(mi.Point3f(dr.detach(self.raw["positions"])), k=cfg.k,
                                     s=cfg.graph_s or None)
            if cfg.use_graph_field:
                self.ds = graph_density_scale(self.graph)
                dr.eval(self.ds)
        self.extent = cfg.extent or _train_extent()
        self.tv_extent = cfg.tv_extent or self.extent
        self.block = np.minimum(cfg.tv_block, np.asarray(self.geo.nVoxel))
        self.rng = np.random.default_rng(1)

    def draw(self, it):
        view = int(self.rng.integers(0, self.geo.n_views))
        start = None
        if self.cfg.lambda_tv > 0 and it % self.cfg.tv_every == 0:
            start = [int(self.rng.integers(0, int(self.geo.nVoxel[a] - self.block[a]) + 1))
                     for a in range(3)]
        return view, start

    def run(self, view, start, tick=None, update=True):
        """One iteration; ``tick(name)`` (if given) synchronises and books a part."""
        import drjit as dr
        import mitsuba as mi
        from mi_grg.core.gaussians import Gaussians
        from mi_grg.core.projector import project_dr
        from mi_grg.core.voxelizer import voxelize_dr
        from mi_grg.training.graph import laplacian_loss
        from mi_grg.training.losses import projection_loss, tv_3d
        try:
            from mi_grg.training.trainer import laplacian_weight
        except ImportError:   # the "before" code: the same weight, as a literal
            from mi_grg.training.trainer import REFERENCE_N

            def laplacian_weight(lam, n):
                return lam * (REFERENCE_N / max(n, 1))
        try:
            from mi_grg.training.trainer import evaluate_gradients
        except ImportError:   # before 2026-11-27: each gradient evaluated where first read
            def evaluate_gradients(*_):
                pass
        cfg, geo = self.cfg, self.geo
        tick = tick or (lambda name, *a: None)
        nv, nu = geo.nDetector
        raw = self.raw
        g = Gaussians.from_raw(raw)
        n = len(g)
        means2d = dr.zeros(mi.Vector2f, n)
        dr.enable_grad(means2d)
        tick("setup")
        img = project_dr(g, geo, angles=geo.angles[view:view + 1], extent=self.extent,
                         density_scale=self.ds, means2d=means2d)
        split = tick("proj_fwd", img)
        if split:   # the loss on a detached copy: its backward and the projector's apart
            img_in = mi.TensorXf(dr.detach(img.array), img.shape)
            dr.enable_grad(img_in)
        else:
            img_in = img
        pred = mi.TensorXf(img_in.array, (nv, nu))
        loss = projection_loss(pred, self.targets[view], cfg.lambda_ssim)
        tick("loss_fwd", loss)
        terms = [loss]
        if start is not None:
            vol = voxelize_dr(g, geo, block=(start, self.block.tolist()), extent=self.tv_extent,
                              density_scale=self.ds)
            tv = (cfg.lambda_tv * cfg.tv_every) * tv_3d(vol)
            tick("tv_fwd", tv)
            terms.append(tv)
        lap = None
        if cfg.lambda_lap > 0 and self.graph is not None:
            lap = laplacian_weight(cfg.lambda_lap, n) * laplacian_loss(self.graph, g.densities,
                                                                       normalise=False)
            tick("lap_fwd", lap)
            terms.append(lap)
        if split:
            dr.backward(loss)
            tick("loss_bwd", dr.grad(img_in.array))
            dr.set_grad(img.array, dr.grad(img_in.array))
            dr.enqueue(dr.ADMode.Backward, img.array)
            dr.traverse(dr.ADMode.Backward)
            # every raw gradient evaluated: each part books its whole chain of derivatives
            grads = lambda: [dr.grad(v) for v in raw.values()]  # noqa: E731
            tick("proj_bwd", *grads(), dr.grad(means2d))
            if start is not None:
                dr.backward(tv)
                tick("tv_bwd", *grads())
            if lap is not None:
                dr.backward(lap)
                tick("lap_bwd", *grads())
            total = loss + sum(terms[1:]) if len(terms) > 1 else loss
        else:
            total = terms[0]
            for t in terms[1:]:
                total = total + t
            dr.backward(total)
            evaluate_gradients(raw, dr.grad(means2d), dr.detach(total))
        grad2d = dr.grad(means2d)
        gnorm = dr.norm(mi.Vector2f(grad2d.x * (nu / 2.0), grad2d.y * (nv / 2.0)))
        if self.densifier.size not in (None, n):
            self.densifier.reset(n)
        self.densifier.accumulate(gnorm, visible=gnorm > 0)
        loss_value = float(dr.detach(total)[0])
        tick("stats_sync")
        grads = {k: dr.grad(v) for k, v in raw.items()}
        if update:
            self.raw = self.optimizer.step(raw)
            tick("adam", self.raw["positions"])
        return loss_value, grads


def _densify_seconds(step) -> float:
    """One clone/split/prune + graph rebuild on the state (not kept)."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.training.graph import build_graph, mean_abs_density_difference
    cfg = step.cfg
    dr.sync_thread()
    t0 = time.perf_counter()
    term = None
    if cfg.use_pga and step.graph is not None:
        term = mean_abs_density_difference(step.graph,
                                           dr.detach(Gaussians.from_raw(step.raw).densities))
    raw, _ = step.densifier.densify_and_prune(dict(step.raw), None, graph_term=term,
                                              bbox=step.geo.bbox(), iteration=1)
    if step.uses_graph:
        build_graph(mi.Point3f(dr.detach(raw["positions"])), k=cfg.k, s=cfg.graph_s or None)
    dr.sync_thread()
    return time.perf_counter() - t0


def worker(method: str, n: int, iters: int, out: str) -> None:
    import mi_grg  # first: picks Dr.Jit's LLVM library and the variant
    import numpy as np
    import drjit as dr
    load0 = os.getloadavg()
    step = _Step(method, n)
    res = {"method": method, "n": n, "code_path": str(Path(mi_grg.__file__).parent),
           "n_gaussians": dr.width(step.raw["raw_densities"])}

    # equality check: loss and gradients of one fixed iteration (no update)
    start = [0, 0, 0] if step.cfg.lambda_tv > 0 else None
    if start is not None:
        start = [int(s // 3) for s in step.geo.nVoxel]
    loss, grads = step.run(3, start, update=False)
    arrays = {"loss": np.float64(loss)}
    for k, v in grads.items():
        arrays[k] = (np.asarray(v) if k == "raw_densities"
                     else np.stack([np.asarray(c) for c in v], -1))
    np.savez(out + ".grads.npz", **arrays)
    for v in step.raw.values():
        dr.clear_grad(v)

    # warm-up (compilation / cache loads) in both modes
    for it in range(4):
        step.run(*step.draw(it))
    times = {p: [] for p in PARTS}

    def make_tick(book):
        last = [time.perf_counter(), time.process_time()]

        def tick(name, *vals):
            if vals:
                dr.eval(*vals)
            dr.sync_thread()
            now, cpu = time.perf_counter(), time.process_time()
            wall_cpu = book.setdefault(name, [0.0, 0.0])
            wall_cpu[0] += now - last[0]
            wall_cpu[1] += cpu - last[1]
            last[:] = [now, cpu]
            return True
        return tick

    split_total, split_cpu, whole_pairs, whole_cpu, kernel_pairs, launches = ([] for _ in range(6))
    cpu_times = {p: [] for p in PARTS}
    for rep in range(iters):
        # split: one pair of iterations (with and without TV), parts booked
        book = {}
        t0, c0 = time.perf_counter(), time.process_time()
        for it in (0, 1):
            step.run(*step.draw(it), tick=make_tick(book))
        split_total.append((time.perf_counter() - t0) / 2)
        split_cpu.append((time.process_time() - c0) / 2)
        for p in PARTS:
            times[p].append(book.get(p, [0.0, 0.0])[0] / 2)
            cpu_times[p].append(book.get(p, [0.0, 0.0])[1] / 2)
        # whole: the same pair without extra synchronisations, kernel history on
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.sync_thread()
        t0, c0 = time.perf_counter(), time.process_time()
        for it in (0, 1):
            step.run(*step.draw(it))
        dr.sync_thread()
        whole_pairs.append((time.perf_counter() - t0) / 2)
        whole_cpu.append((time.process_time() - c0) / 2)
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hist = dr.kernel_history()
        kernel_pairs.append(sum(h.get("execution_time", 0.0) for h in hist) / 2e3)
        launches.append(len(hist) / 2)
    res["parts_s"] = {p: statistics.median(v) for p, v in times.items()}
    res["parts_cpu_s"] = {p: statistics.median(v) for p, v in cpu_times.items()}
    res["split_step_s"] = statistics.median(split_total)
    res["split_step_cpu_s"] = statistics.median(split_cpu)
    res["step_s"] = statistics.median(whole_pairs)
    res["step_cpu_s"] = statistics.median(whole_cpu)
    res["kernel_s"] = statistics.median(kernel_pairs)
    res["outside_kernels_s"] = statistics.median(w - k for w, k in zip(whole_pairs, kernel_pairs))
    res["launches_per_iteration"] = statistics.median(launches)
    res["iterations_timed"] = 2 * iters
    interval = max(1, int(step.cfg.densify_interval * max(step.iterations / 30000.0, 0.25)))
    res["densify_s"] = _densify_seconds(step)
    res["densify_interval"] = interval
    res["densify_amortised_s"] = res["densify_s"] / interval
    res["loadavg_before"] = load0
    res["loadavg_after"] = os.getloadavg()
    res["n_gaussians_end"] = dr.width(step.raw["raw_densities"])
    Path(out).write_text(json.dumps(res))


# ====================================================================== frozen vs traced
def _frozen_adapter(step):
    """A Recording (mi_grg.training.recording) of ``step``'s iteration."""
    from mi_grg.training.recording import Recording
    from mi_grg.training.step import StepConfig, TVTerm
    cfg = step.cfg
    step.said, step.view_arrays = [], {}
    tv = TVTerm(cfg.lambda_tv * cfg.tv_every, tuple(int(b) for b in step.block),
                float(step.tv_extent))
    return Recording(StepConfig(step.geo, float(step.extent), cfg.lambda_ssim, tv,
                                float(cfg.lambda_lap)), log=step.said.append)


def _step_inputs(step, view, start):
    """mi_grg.training.step.StepInputs of ``step``'s state (as Trainer._step_inputs)."""
    import drjit as dr
    from mi_grg.training.step import StepInputs, laplacian_weight, view_arrays
    if view not in step.view_arrays:
        step.view_arrays[view] = view_arrays(step.geo, view)
    lap = None
    if step.cfg.lambda_lap > 0 and step.graph is not None:
        lap = laplacian_weight(step.cfg.lambda_lap, dr.width(step.raw["raw_densities"]))
    return StepInputs(step.raw, step.view_arrays[view], step.targets[view], step.ds,
                      step.graph, lap, start)


def _frozen_run(step, fz, it):
    """One iteration by the recorded step (traced where it hands it back), updated as
    Trainer._step does: 1 if replayed."""
    import drjit as dr
    view, start = step.draw(it)
    inputs = _step_inputs(step, view, start)
    stats = step.densifier.recorded_inputs(dr.width(step.raw["raw_densities"]))
    adam = step.optimizer.recorded_inputs(step.raw)
    update = None if stats is None or adam is None else {"stats": stats, "adam": adam}
    done = fz.step(inputs, update, (step.optimizer.betas, step.optimizer.eps))
    if done is None:
        step.run(view, start)
        return 0
    out = done[0]
    if update is None:
        step.densifier.accumulate(out["gnorm"], visible=out["gnorm"] > 0)
        step.raw = step.optimizer.step(step.raw, grads=out["grads"])
    else:
        step.densifier.add(out["stats"])
        step.raw = step.optimizer.apply(out["raw"], out["m"], out["v"])
    return 1


def _timed_pairs(run_one, iters):
    """(wall per iteration, kernels per iteration, launches) of ``iters`` pairs."""
    import drjit as dr
    walls, kernels, launches = [], [], []
    for _ in range(iters):
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.sync_thread()
        t0 = time.perf_counter()
        for it in (0, 1):
            run_one(it)
        dr.sync_thread()
        walls.append((time.perf_counter() - t0) / 2)
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hist = dr.kernel_history()
        kernels.append(sum(h.get("execution_time", 0.0) for h in hist) / 2e3)
        launches.append(len(hist) / 2)
    med = statistics.median
    return {"wall_s": med(walls), "kernel_s": med(kernels),
            "outside_s": med(w - k for w, k in zip(walls, kernels)), "launches": med(launches)}


def _frozen_equality(step, fz) -> dict:
    """Largest difference of loss and gradients, frozen vs traced, on one fixed iteration
    (relative to the loss / each gradient's largest entry)."""
    import numpy as np
    import drjit as dr
    start = None
    if step.cfg.lambda_tv > 0:
        start = [int(min(s // 3, s - b)) for s, b in zip(step.geo.nVoxel, step.block)]
    loss, grads = step.run(3, start, update=False)
    for v in step.raw.values():
        dr.clear_grad(v)
    for _ in range(3):          # the first calls may overflow their capacity and re-record
        out, key = fz.run(_step_inputs(step, 3, start))
        floss = fz.check(out, key)
        if floss is not None:
            break
    res = {"loss_rel": abs(floss - loss) / max(abs(loss), 1e-30)}
    for k, g in grads.items():
        a, b = np.asarray(g, np.float64), np.asarray(out["grads"][k], np.float64)
        res[k] = float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-30))
    return res


def frozen_worker(method: str, n: int, iters: int, blocks: int, out: str) -> None:
    import mi_grg  # noqa: F401  (first: picks Dr.Jit's LLVM library and the variant)
    import drjit as dr
    load0 = os.getloadavg()
    step = _Step(method, n)
    fz = _frozen_adapter(step)
    res = {"method": method, "n": n, "n_gaussians": dr.width(step.raw["raw_densities"]),
           "equality": _frozen_equality(step, fz)}
    for it in range(8):         # warm-up: compilation, recordings, capacities
        step.run(*step.draw(it))
        _frozen_run(step, fz, it)
    res["recordings_warmup"] = fz.n_recordings
    replayed = [0]

    def frozen_one(it):
        replayed[0] += _frozen_run(step, fz, it)
    res["blocks"] = []
    for _ in range(blocks):
        traced = _timed_pairs(lambda it: step.run(*step.draw(it)), iters)
        frozen = _timed_pairs(frozen_one, iters)
        res["blocks"].append({"traced": traced, "frozen": frozen})
    res["replayed"], res["iterations_frozen"] = replayed[0], 2 * iters * blocks
    res["recordings"], res["notes"] = fz.n_recordings, step.said
    res["loadavg_before"], res["loadavg_after"] = load0, os.getloadavg()
    Path(out).write_text(json.dumps(res))


def _frozen_cell(runs: list) -> dict:
    med = statistics.median
    cell = {"method": runs[0]["method"], "n": runs[0]["n"],
            "n_gaussians": runs[0]["n_gaussians"], "runs": runs}
    blocks = [b for r in runs for b in r["blocks"]]
    for mode in ("traced", "frozen"):
        cell[mode] = {k: med(b[mode][k] for b in blocks)
                      for k in ("wall_s", "kernel_s", "outside_s", "launches")}
    cell["ratio_wall"] = med(b["frozen"]["wall_s"] / b["traced"]["wall_s"] for b in blocks)
    cell["ratio_outside"] = med(b["frozen"]["outside_s"] / max(b["traced"]["outside_s"], 1e-9)
                                for b in blocks)
    cell["replayed"] = sum(r["replayed"] for r in runs)
    cell["iterations_frozen"] = sum(r["iterations_frozen"] for r in runs)
    cell["equality"] = {k: max(r["equality"][k] for r in runs) for k in runs[0]["equality"]}
    return cell


def _frozen_markdown(meta, cells) -> str:
    ms = lambda s: f"{1e3 * s:.1f}"  # noqa: E731
    lines = ["# The recorded (frozen) training step against the traced one "
             "(`bench/train_step.py --frozen`)", "",
             f"{meta['date']}, {meta['cpus']} CPUs ({meta['machine']}), {meta['variant']}, "
             f"code `{meta['after']}`. {meta['rounds']} process(es) per cell, each "
             f"alternating {meta['blocks']} blocks of {meta['iters']} traced and "
             f"{meta['iters']} frozen iteration pairs (medians over the blocks; a ratio is "
             "taken within each alternation, then its median). An iteration as Trainer.run "
             "composes it (view, TV block every tv_every-th iteration, Laplacian, "
             "backward, statistics, Adam), on the late-training state of the "
             "train_step bench. Load = os.getloadavg() (1 min) at each process's start.", ""]
    for c in cells:
        t, f = c["traced"], c["frozen"]
        lines += [f"## {c['method']} at {c['n']}^3 ({c['n_gaussians']} Gaussians)", "",
                  "| per iteration | traced | frozen | frozen / traced |", "|---|---|---|---|",
                  f"| wall, ms | {ms(t['wall_s'])} | {ms(f['wall_s'])} | {c['ratio_wall']:.2f} |",
                  f"| inside kernels, ms | {ms(t['kernel_s'])} | {ms(f['kernel_s'])} | |",
                  f"| outside kernels (tracing, launches, syncs), ms | {ms(t['outside_s'])} | "
                  f"{ms(f['outside_s'])} | {c['ratio_outside']:.2f} |",
                  f"| kernel launches | {t['launches']:.0f} | {f['launches']:.0f} | |", ""]
        eq = c["equality"]
        worst = max(v for k, v in eq.items() if k != "loss_rel")
        loads = ", ".join(f"{r['loadavg_before'][0]:.1f}" for r in c["runs"])
        notes = sorted({x for r in c["runs"] for x in r["notes"]})
        lines += [f"Replayed {c['replayed']} of {c['iterations_frozen']} timed frozen "
                  "iterations (the others ran traced after a capacity overflow). Same "
                  f"state, view and TV block, frozen vs traced: loss relative difference "
                  f"{eq['loss_rel']:.1e}, largest gradient difference {worst:.1e} of that "
                  f"gradient's largest entry. Load at process start: {loads}."]
        lines += ([""] + [f"Log: {x}" for x in notes]) if notes else []
        lines.append("")
    return "\n".join(lines)


def _machine(variant: str) -> str:
    """The host's processor, and on CUDA the GPU's name, so that each figure names its device."""
    host = platform.processor() or platform.machine()
    if not variant.startswith("cuda"):
        return host
    try:
        gpu = subprocess.check_output(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                      text=True).strip().splitlines()[0]
    except Exception:   # noqa: BLE001
        gpu = "unnamed GPU"
    return f"{gpu}, host {host}"


def frozen_main(args) -> int:
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            for method in args.methods:
                if not state_path(method, n).exists():
                    print(f"training the {method} {n}^3 state ...", flush=True)
                    _spawn(["--make-state", method, str(n), str(TRAIN_ITERS.get(n, 400))])
                runs = []
                for r in range(args.rounds):
                    out = os.path.join(tmp, f"frozen_{method}_{n}_{r}.json")
                    print(f"{method} {n}^3 frozen vs traced, process {r + 1}/{args.rounds}",
                          flush=True)
                    _spawn(["--frozen-worker", method, str(n), str(args.iters),
                            str(args.blocks), out])
                    runs.append(json.loads(Path(out).read_text()))
                cells.append(_frozen_cell(runs))
    meta = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            **_run_meta(args), "rounds": args.rounds, "blocks": args.blocks,
            "iters": args.iters}
    return _write(args, "train_step_frozen", meta, cells, _frozen_markdown)


def _run_meta(args) -> dict:
    """Where and on which code a bench run measured."""
    return {"machine": _machine(args.variant), "cpus": os.cpu_count(),
            "after": _git("rev-parse", "--short", "HEAD") + (" + working tree" if
                                                             _git("status", "--porcelain") else ""),
            "variant": args.variant}


def _write(args, name: str, meta: dict, cells: list, markdown) -> int:
    """docs/bench/NAME[_cuda].{json,md} (or under --out), and the table printed."""
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    name += "_cuda" if args.variant.startswith("cuda") else ""
    (outdir / f"{name}.json").write_text(json.dumps({"meta": meta, "cells": cells}, indent=1))
    (outdir / f"{name}.md").write_text(markdown(meta, cells))
    print((outdir / f"{name}.md").read_text())
    return 0


# ====================================================================== harness
def _export(rev: str) -> Path:
    sha = subprocess.check_output(["git", "rev-parse", rev], cwd=ROOT, text=True).strip()
    dest = CACHE / f"code_{sha[:10]}"
    if not (dest / "mi_grg" / "__init__.py").exists():
        dest.mkdir(parents=True, exist_ok=True)
        tar = subprocess.run(["git", "archive", sha, "mi_grg"], cwd=ROOT, check=True,
                             capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    return dest


def _spawn(args: list, pythonpath: Path | None = None) -> None:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath) + os.pathsep + env.get("PYTHONPATH", "")
    subprocess.run([sys.executable, __file__] + args, check=True, env=env, cwd=ROOT)


def _compare(a: str, b: str) -> dict:
    import numpy as np
    fa, fb = np.load(a), np.load(b)
    out = {"loss_rel": float(abs(fa["loss"] - fb["loss"]) / max(abs(float(fa["loss"])), 1e-30))}
    for k in fa.files:
        if k == "loss":
            continue
        x, y = fa[k].astype(np.float64), fb[k].astype(np.float64)
        out[k] = float(np.abs(x - y).max() / max(np.abs(x).max(), 1e-30))
    return out


def _git(*a) -> str:
    try:
        return subprocess.check_output(["git", *a], cwd=ROOT, text=True).strip()
    except Exception:   # noqa: BLE001
        return "?"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64])
    ap.add_argument("--methods", nargs="+", default=["gr", "r2"])
    ap.add_argument("--before", default=REFERENCE, help="git revision of the 'before' code "
                    f"(default {REFERENCE}: the code before issue 21's speed work); 'none' "
                    "skips it")
    ap.add_argument("--iters", type=int, default=10, help="timed iteration pairs per process")
    ap.add_argument("--rounds", type=int, default=2, help="before/after alternations")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--variant", default="llvm_ad_mono", choices=("llvm_ad_mono", "cuda_ad_mono"),
                    help="every process runs on it; cuda writes train_step_cuda.{md,json}")
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench"))
    ap.add_argument("--worker", nargs=4, metavar=("METHOD", "N", "ITERS", "OUT"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--make-state", nargs=3, metavar=("METHOD", "N", "ITERS"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--frozen", action="store_true", help="time the frozen step against the "
                    "traced one (writes train_step_frozen*.{md,json})")
    ap.add_argument("--blocks", type=int, default=3, help="--frozen: traced/frozen "
                    "alternations per process")
    ap.add_argument("--frozen-worker", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.frozen_worker:
        m, n, it, b, out = args.frozen_worker
        frozen_worker(m, int(n), int(it), int(b), out)
        return 0
    if args.worker:
        m, n, it, out = args.worker
        worker(m, int(n), int(it), out)
        return 0
    if args.make_state:
        m, n, it = args.make_state
        make_state(m, int(n), int(it))
        return 0
    if args.quick:
        args.iters, args.rounds = 3, 1
    os.environ["MI_GRG_VARIANT"] = args.variant   # inherited by every process (_spawn)
    if args.frozen:
        if args.quick:
            args.blocks = 1
        return frozen_main(args)
    before = args.before
    codes = [("after", None)]
    if before.lower() != "none":
        codes.insert(0, ("before", _export(before)))
    cells = []
    for n in args.sizes:
        for method in args.methods:
            if not state_path(method, n).exists():
                print(f"training the {method} {n}^3 state ({TRAIN_ITERS.get(n, 400)} it) ...",
                      flush=True)
                _spawn(["--make-state", method, str(n), str(TRAIN_ITERS.get(n, 400))])
            runs = {label: [] for label, _ in codes}
            with tempfile.TemporaryDirectory() as tmp:
                for r in range(args.rounds):
                    for label, path in (codes if r % 2 == 0 else codes[::-1]):
                        out = os.path.join(tmp, f"{label}_{r}.json")
                        print(f"{method} {n}^3 {label} round {r + 1}/{args.rounds}", flush=True)
                        _spawn(["--worker", method, str(n), str(args.iters), out], path)
                        runs[label].append(json.loads(Path(out).read_text()))
                equal = (_compare(os.path.join(tmp, "before_0.json.grads.npz"),
                                  os.path.join(tmp, "after_0.json.grads.npz"))
                         if "before" in runs else None)
            cell = {"method": method, "n": n, "equality_vs_before": equal}
            for label, rs in runs.items():
                med = lambda key: statistics.median(r[key] for r in rs)  # noqa: E731
                cell[label] = {"n_gaussians": rs[0]["n_gaussians"],
                               "densify_interval": rs[0]["densify_interval"], "runs": rs}
                for key in ("step_s", "step_cpu_s", "kernel_s", "outside_kernels_s",
                            "split_step_s", "split_step_cpu_s", "launches_per_iteration",
                            "densify_amortised_s", "densify_s"):
                    cell[label][key] = med(key)
                for key in ("parts_s", "parts_cpu_s"):
                    cell[label][key] = {p: statistics.median(r[key][p] for r in rs)
                                        for p in PARTS}
            cells.append(cell)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), **_run_meta(args), "before": before,
            "iters_per_process": 2 * args.iters, "rounds": args.rounds}
    return _write(args, "train_step", meta, cells, _markdown)


def _markdown(meta, cells) -> str:
    ms = lambda s: f"{1e3 * s:.1f}"  # noqa: E731
    lines = ["# One training iteration, split into its parts (`bench/train_step.py`)", "",
             f"{meta['date']}, {meta['cpus']} CPUs ({meta['machine']}), {meta.get('variant', 'llvm_ad_mono')}. "
             f"before = `{meta['before'][:10]}`, after = `{meta['after']}`. Each cell: "
             f"{meta['rounds']} process(es) per code, alternated, each timing "
             f"{meta['iters_per_process']} iterations (medians; the table gives the median "
             "over processes). Wall = elapsed time; CPU = the process's CPU time (all "
             "threads), which a loaded machine inflates much less than the wall time. "
             "Load = os.getloadavg() (1 min) at each process's start.", ""]
    for c in cells:
        labels = [k for k in ("before", "after") if k in c]
        both = len(labels) == 2
        lines += [f"## {c['method']} at {c['n']}^3 ({c[labels[-1]]['n_gaussians']} Gaussians)",
                  "", "| ms per iteration | " + " | ".join(f"{k} wall" for k in labels) + " | "
                  + " | ".join(f"{k} CPU" for k in labels) + (" | after / before (CPU) |"
                                                               if both else " |"),
                  "|---|" + "---|" * (2 * len(labels) + both)]

        def row(name, wall, cpu):
            r = f"| {name} | " + " | ".join(ms(v) for v in wall + cpu)
            if both:
                r += f" | {cpu[1] / cpu[0]:.2f}" if cpu[0] > 0 else " | -"
            return r + " |"
        for p in PARTS:
            lines.append(row(PART_TEXT[p], [c[k]["parts_s"][p] for k in labels],
                             [c[k]["parts_cpu_s"][p] for k in labels]))
        lines.append(row("**sum of parts (synchronised after each)**",
                         [c[k]["split_step_s"] for k in labels],
                         [c[k]["split_step_cpu_s"] for k in labels]))
        lines.append(row("**whole iteration (as the trainer runs it)**",
                         [c[k]["step_s"] for k in labels], [c[k]["step_cpu_s"] for k in labels]))
        lines += ["", "| whole iteration, wall ms | " + " | ".join(labels) + " |",
                  "|---|" + "---|" * len(labels)]
        for key, name in (("kernel_s", "inside kernels (Dr.Jit kernel history)"),
                          ("outside_kernels_s", "outside kernels (tracing, launches, host syncs)"),
                          ("densify_amortised_s", "densification + graph rebuild, amortised "
                           "over its interval (inside the window only)")):
            lines.append(f"| {name} | " + " | ".join(ms(c[k][key]) for k in labels) + " |")
        lines.append("| kernel launches per iteration | " + " | ".join(
            f"{c[k]['launches_per_iteration']:.0f}" for k in labels) + " |")
        loads = "; ".join(f"{k}: " + ", ".join(f"{r['loadavg_before'][0]:.1f}"
                                               for r in c[k]["runs"]) for k in labels)
        lines += ["", f"Load at process start: {loads}."]
        eq = c.get("equality_vs_before")
        if eq:
            worst = max(v for k, v in eq.items() if k != "loss_rel")
            lines += ["", f"Same state, view and TV block, before vs after: loss relative "
                      f"difference {eq['loss_rel']:.1e}; largest gradient difference "
                      f"{worst:.1e} of that gradient's largest entry ("
                      + ", ".join(f"{k} {v:.1e}" for k, v in eq.items() if k != "loss_rel")
                      + ")."]
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
