"""A training iteration recorded once with Dr.Jit's frozen functions (``dr.freeze``) and
replayed: no Python tracing, no host read inside it.

What is recorded: Gaussians.from_raw -> the projection of one view (with means2d) -> L1 +
D-SSIM -> TV on the iteration's block (every ``tv_every``-th iteration; a recording of its
own) -> the graph Laplacian -> backward -> the densification statistics -> Adam (the
moments and new parameters are outputs, applied once the replay is checked; Adam stays
traced when it checks gradients for NaN on every step). What stays outside
(``Trainer._step``): the draws (view, block corner), the loss read (the one host
synchronisation of an iteration, as on the traced path), evaluation, logging,
densification and graph rebuilds.

The traced step reads data-dependent sizes on the host (the projector's footprint rows and
near-source records, the voxelizer's pair plan); a recording cannot. Here they are
capacities fixed when the step is recorded: ``rows`` (record, row) lanes and ``near``
near-source record slots (none until one is seen) for the projection (``RowCapacity``),
``cols`` column and ``slices`` slice lanes for the TV block
(``voxelizer.capacity_plan``). The lanes past the counts are the tail of each launch and
run inside a symbolic conditional, so whole SIMD packets of them skip their work (a
masked lane costs about a real one's set-up otherwise). The counts come back
with the result; a count past its capacity discards the result, the iteration runs
traced, the capacity grows and the next call records anew. Each kind of event is said once (``FrozenStep.note``).
Recordings are keyed by the Gaussian count, the graph's sizes and the capacities:
densification and graph rebuilds record anew.

Exact: the recorded step evaluates the same expressions as the traced one; only the lane
counts differ (lanes past the counts add nothing). docs/frozen_step.md lists the traced step's host
reads and where each went.
"""
from __future__ import annotations

import gc
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.projector import _ProjectionSetup, _ProjectOp
from mi_grg.core.projector_chunks import RowCapacity
from mi_grg.core.projector_records import DetectorConstants, ViewFrameArrays
from mi_grg.core.view_frames import view_frames
from mi_grg.core.voxelizer import voxelize_block_capacity
from mi_grg.training.densify import add_one_view
from mi_grg.training.optim import adam_update

# Headroom of a capacity over the most lanes per Gaussian seen so far (the rows vary with
# the view, the pairs with the block), and its granularity (so that small changes keep a
# recording)
HEADROOM = 1.25
QUANTUM = {"rows": 4096, "cols": 4096, "slices": 4096, "near": 16}
# Lanes (near: records) per Gaussian before any count was seen (an overflow then sets
# the real one); near-source records are rare: none until one is seen
INITIAL_PER_GAUSSIAN = {"rows": 4.0, "cols": 2.0, "slices": 1.0, "near": 0.0}
# Floats of a view's detector-value input (6 used)
DETECTOR_PAD = 16


class _Static:
    """The step's Python constants (not a PyTree: the frozen function hashes it by id)."""

    def __init__(self, geometry, extent, lambda_ssim, tv):
        self.geometry, self.extent, self.lambda_ssim = geometry, float(extent), lambda_ssim
        self.nv, self.nu = geometry.nDetector
        self.frames = view_frames(geometry.with_angles(geometry.angles[:1]))
        # (weight lambda_tv x tv_every, block size [3], support) or None
        self.tv = None if tv is None else (tv[0], tuple(int(x) for x in tv[1]), float(tv[2]))


class _PairCapacity:
    """The TV block's column and slice lanes; the plan leaves the totals it needed."""

    def __init__(self, cols: int, slices: int):
        self.cols, self.slices = int(cols), int(slices)
        self.cols_total = self.slices_total = None


def _owned(x):
    """A copy of ``x`` in Dr.Jit's own memory: arrays made from NumPy may map host memory,
    whose alignment (part of a recording's key) varies from array to array."""
    y = dr.empty(type(x), dr.width(x))
    dr.scatter(y, x, dr.arange(mi.UInt32, dr.width(x)))
    dr.eval(y)
    return y


def _view_inputs(geometry) -> list:
    """Per view, the frame arrays project_dr builds for that view alone (a PyTree): an
    input of the step, so that one recording serves every view. (Where the detector
    constants are the same for every view (``ViewFrames.shared``) they are built inside,
    as width-1 inputs would make a recording depend on their addresses' alignment; a
    per-view scan's own are a padded input ``det``.)"""
    out = []
    shared = view_frames(geometry).shared
    for v in range(geometry.n_views):
        fr = view_frames(geometry.with_angles(geometry.angles[v:v + 1]))
        fa = ViewFrameArrays(fr)
        out.append({"e": [[_owned(c) for c in axis] for axis in fa.e],
                    "o": [_owned(c) for c in fa.o]})
        if not shared:
            # a per-view scan whose detector values differ: they are inputs too, padded
            # (a width-1 input's alignment would key the recording)
            vals = np.zeros(DETECTOR_PAD, np.float32)
            h, a_u, a_v, du, dv = fr.detector_values(0)
            vals[:6] = (h, h * h, a_u, a_v, du, dv)    # h^2 rounded once, as DetectorConstants
            out[-1]["det"] = _owned(mi.Float(vals))
    return out


def _detector(static: _Static, view: dict) -> DetectorConstants:
    """The drawn view's detector constants: built inside from the first view where all
    views share them, read from the inputs (``view["det"]``) where they differ."""
    det = DetectorConstants(static.frames, static.geometry, static.extent)
    if "det" in view:
        vals = [dr.gather(mi.Float, view["det"], mi.UInt32(k)) for k in range(6)]
        det.h, det.h2, det.a_u, det.a_v, det.du, det.dv = vals
    return det


def _setup(static: _Static, inputs: dict, n: int, caps: tuple) -> _ProjectionSetup:
    """project_dr's setup of the drawn view with capacities ``caps`` (rows, near
    records), the view's frame arrays from the inputs; project_dr's input checks (host
    reads) are left out (the loss read stays outside)."""
    fa = object.__new__(ViewFrameArrays)
    fa.e, fa.o = inputs["view"]["e"], inputs["view"]["o"]
    det = _detector(static, inputs["view"])
    setup = _ProjectionSetup(static.geometry, fa, det, n, 1)
    setup.caps = RowCapacity(*caps)
    return setup


def _tv_term(static: _Static, inputs: dict, g: Gaussians, pairs: _PairCapacity):
    """The weighted TV of the block at ``inputs["tv_start"]``, as Trainer._step has it."""
    from mi_grg.training.losses import tv_3d
    weight, size, support = static.tv
    vol = voxelize_block_capacity(g, static.geometry, inputs["tv_start"], size, support,
                                  inputs["ds"], pairs)
    return weight * tv_3d(vol)


def _step_body(static: _Static, inputs: dict, key: tuple) -> dict:
    """The recorded iteration; ``key`` = (N, (rows, near records), graph sizes, (cols,
    slices) or None, Adam's (betas, eps) or None) keys the recordings (the capacities
    become the lane counts)."""
    from mi_grg.training.graph import laplacian_loss
    from mi_grg.training.losses import projection_loss
    raw = {}
    for k, v in inputs["raw"].items():
        raw[k] = type(v)(dr.detach(v))
        dr.enable_grad(raw[k])
    g = Gaussians.from_raw(raw)
    means2d = dr.zeros(mi.Vector2f, len(g))
    dr.enable_grad(means2d)
    setup = _setup(static, inputs, len(g), key[1])
    img = dr.custom(_ProjectOp, g.positions, g.scales, g.rotations, g.densities,
                    inputs["ds"], means2d, setup)
    loss = projection_loss(mi.TensorXf(img, (static.nv, static.nu)), inputs["target"],
                           static.lambda_ssim)
    pairs = None
    if key[3] is not None:
        pairs = _PairCapacity(*key[3])
        loss = loss + _tv_term(static, inputs, g, pairs)
    if inputs["graph"] is not None:
        lap = laplacian_loss(inputs["graph"], g.densities, normalise=False)
        loss = loss + inputs["lap_weight"] * lap
    dr.backward(loss)
    grad2d = dr.grad(means2d)
    gnorm = dr.norm(mi.Vector2f(grad2d.x * (static.nu / 2.0), grad2d.y * (static.nv / 2.0)))
    U = mi.UInt32
    counts = [setup.caps.rows_total, setup.caps.near_count]
    counts += ([pairs.cols_total, pairs.slices_total] if pairs is not None
               else [dr.zeros(U, 1), dr.zeros(U, 1)])
    grads = {k: dr.grad(v) for k, v in raw.items()}
    dr.eval(grads, gnorm)        # every group's gradient in one kernel (evaluate_gradients)
    out = {"loss": dr.detach(loss), "grads": grads, "gnorm": gnorm,
           "counts": [U(c) for c in counts]}
    _update_body(inputs, key, out)
    dr.eval(out)
    return out


def _update_body(inputs: dict, key: tuple, out: dict) -> None:
    """The densification statistics and Adam, recorded too when given (``inputs["stats"]``,
    ``inputs["adam"]``; betas and eps in ``key[4]``): the same functions as
    ``PGADensifier.accumulate`` and ``Adam.step`` use. Results go into ``out``."""
    stats, adam = inputs["stats"], inputs["adam"]
    if stats is not None:
        g = dr.detach(out["gnorm"])
        out["stats"] = add_one_view(stats["grad_accum"], stats["view_count"], g, g > 0)
    if adam is None:
        return
    betas, eps = key[4]
    out["raw"], out["m"], out["v"] = {}, {}, {}
    for name, p in inputs["raw"].items():
        new, m, v = adam_update(p, dr.detach(out["grads"][name]), adam["m"][name],
                                adam["v"][name], betas, eps, adam["step_size"][name],
                                adam["inv_bc2"][name])
        dr.eval(new, m, v)       # one kernel per group, as Adam.step
        out["raw"][name], out["m"][name], out["v"][name] = new, m, v


class FrozenStep:
    """The recorded training iteration of a ``Trainer`` (see the module docstring).

    ``iteration(trainer, it, raw, view, start, laplacian_weight)`` returns (new raw, loss
    value), or None when this iteration must run traced (the caller then runs its own
    step: nothing of the recorded run is kept). ``lambda_lap``: the graph Laplacian's
    weight (TrainConfig's, scaled per call by ``laplacian_weight``; 0: no Laplacian).
    ``tv``: (weight, block size, support) of the TV term, or None."""

    def __init__(self, geometry, extent, lambda_ssim, lambda_lap, tv=None, log=print):
        self.static = _Static(geometry, extent, lambda_ssim, tv)
        self.lambda_lap = float(lambda_lap)   # the Laplacian's weight before its scaling
        self.views = _view_inputs(geometry)
        self.targets = {}
        # one recording per kind of iteration (with and without TV block), replaced when
        # its key changes; re-recording after a densification is expected, not a warning
        self.fn = {False: dr.freeze(_step_body, limit=1, warn_after=1 << 30),
                   True: dr.freeze(_step_body, limit=1, warn_after=1 << 30)}
        self.per_gaussian = dict(INITIAL_PER_GAUSSIAN)
        self.capacity = {}          # kind -> (N, lanes) of the current recordings
        self.log, self.said = log, set()
        self.replays = self.fallbacks = 0

    @property
    def n_recordings(self) -> int:
        return sum(f.n_recordings for f in self.fn.values())

    def note(self, kind: str, text: str) -> None:
        """Say ``text`` once per kind of event (overflows are expected after growth)."""
        if kind not in self.said:
            self.said.add(kind)
            self.log(f"frozen step: {text}")

    def _target(self, view: int, target):
        """The view's target image in Dr.Jit's own memory (see ``_owned``), kept."""
        kept = self.targets.get(view)
        if kept is None or kept[0] is not target:
            kept = self.targets[view] = (target, mi.TensorXf(_owned(target.array),
                                                             target.shape))
        return kept[1]

    def lanes(self, kind: str, n: int) -> int:
        """Lanes of ``kind`` for N Gaussians: the most per Gaussian seen, with headroom."""
        cap = self.capacity.get(kind)
        if cap is None or cap[0] != n:
            quantum = QUANTUM[kind]
            q = math.ceil(self.per_gaussian[kind] * HEADROOM * max(n, 1) / quantum)
            cap = self.capacity[kind] = (n, q * quantum)
        return cap[1]

    def run(self, raw: dict, view: int, target, graph, density_scale, lap_weight,
            start=None, update=None):
        """The recorded computation on this state (lazy outputs of the replay: loss,
        grads, gnorm, counts; with ``update`` (``_update_inputs``) also stats, raw, m, v)
        and the key it ran under. ``start``: the TV block's corner (None: no TV)."""
        n = dr.width(raw["raw_densities"])
        if graph is not None:
            from mi_grg.training.graph import neighbour_table
            neighbour_table(graph)       # its host read, once per graph, outside
        tv = start is not None
        key = (n, (self.lanes("rows", n), self.lanes("near", n)), None if graph is None else
               (graph.n, graph.num_edges, graph.table[0]),
               (self.lanes("cols", n), self.lanes("slices", n)) if tv else None,
               update[1] if update is not None else None)
        inputs = {"raw": {k: dr.detach(v) for k, v in raw.items()},
                  "view": self.views[view], "target": self._target(view, target),
                  "ds": density_scale,
                  "graph": graph, "lap_weight": lap_weight if graph is not None else None,
                  "tv_start": [dr.opaque(mi.Int32, int(s)) for s in start] if tv else None,
                  "stats": update[0]["stats"] if update is not None else None,
                  "adam": update[0]["adam"] if update is not None else None}
        # Python's cycle collector must not run inside a recording or replay: collecting
        # another (dead) trainer's recorded function there aborts Dr.Jit.
        paused = gc.isenabled()
        gc.disable()
        try:
            return self.fn[tv](self.static, inputs, key), key
        finally:
            if paused:
                gc.enable()

    def check(self, out: dict, key: tuple) -> float | None:
        """The loss value, or None: the result is incomplete (said once per kind); the
        capacity that overflowed grows for the next call."""
        vals = [np.asarray(out["loss"], np.float64).reshape(-1)[0]]
        vals += [int(np.asarray(c).reshape(-1)[0]) for c in out["counts"]]
        loss, rows, near, cols, slices = vals
        n = key[0]
        caps = {"rows": (rows, key[1][0]), "near": (near, key[1][1])}
        if key[3] is not None:
            caps.update(cols=(cols, key[3][0]), slices=(slices, key[3][1]))
        over = []
        for kind, (count, lanes) in caps.items():
            self.per_gaussian[kind] = max(self.per_gaussian[kind], count / max(n, 1))
            if count > lanes:
                over.append(f"{count} {kind} > {lanes}")
                self.capacity.pop(kind, None)      # the next call records with room
        if over:
            self.note("overflow", "lanes past the recorded capacity (" + ", ".join(over)
                      + "): the iteration runs traced and the next records a larger "
                      "capacity (said once)")
            return None
        return float(loss)

    def iteration(self, trainer, it: int, raw: dict, view: int, start, laplacian_weight):
        """One iteration of ``trainer``: (new raw, loss value), or None (run it traced).
        ``start``: the TV block's corner or None; ``laplacian_weight(lambda_lap, n)``:
        the trainer's weight of the Laplacian term."""
        from mi_grg.core.projector import RECORDS_PER_CHUNK
        n = dr.width(raw["raw_densities"])
        if n == 0 or n > RECORDS_PER_CHUNK or (start is not None and self.static.tv is None):
            self.note("chunks", f"{n} Gaussians (or a TV block without its settings): "
                      "not recordable, traced")
            self.fallbacks += 1
            return None
        lap_weight = None
        if self.lambda_lap > 0 and trainer.graph is not None:
            lap_weight = laplacian_weight(self.lambda_lap, n)
        graph = trainer.graph if lap_weight is not None else None
        update = _update_inputs(trainer, raw, n)
        out, key = self.run(raw, view, trainer.targets[view], graph,
                            trainer._density_scale, lap_weight, start, update)
        loss_value = self.check(out, key)
        if loss_value is None:
            self.fallbacks += 1
            return None
        self.replays += 1
        if not math.isfinite(loss_value):
            raise FloatingPointError(f"loss is {loss_value} at iteration {it}")
        return _commit(trainer, raw, out, update), loss_value


def _update_inputs(trainer, raw: dict, n: int):
    """(inputs, key part) of the statistics and Adam for a recording, or None where they
    stay traced: Adam's per-step finite check (a host read), or a state that does not
    match N (the traced calls then raise their errors)."""
    opt, dens = trainer.optimizer, trainer.densifier
    if dens.size is None:
        dens.reset(n)             # as accumulate does on its first call
    if opt.check_finite or dens.size != n or set(raw) - set(opt.lr0):
        return None
    states = {name: opt.group_state(name, p) for name, p in raw.items()}
    if any(dr.width(st.m) != n for st in states.values()):
        return None
    scalars = {name: opt.step_scalars(name, st.step + 1) for name, st in states.items()}
    adam = {"m": {k: st.m for k, st in states.items()},
            "v": {k: st.v for k, st in states.items()},
            "step_size": {k: dr.opaque(mi.Float, a) for k, (a, _) in scalars.items()},
            "inv_bc2": {k: dr.opaque(mi.Float, b) for k, (_, b) in scalars.items()}}
    stats = {"grad_accum": dens.grad_accum, "view_count": dens.view_count}
    return {"stats": stats, "adam": adam}, (opt.betas, opt.eps)


def _commit(trainer, raw: dict, out: dict, update) -> dict:
    """Apply a checked replay: the statistics and Adam's state (recorded), or run them
    traced (``update`` None). Returns the new raw parameters."""
    if update is None:
        trainer.densifier.accumulate(out["gnorm"], visible=out["gnorm"] > 0)
        return trainer.optimizer.step(raw, grads=out["grads"])
    trainer.densifier.grad_accum, trainer.densifier.view_count = out["stats"]
    new = {}
    for name in raw:
        st = trainer.optimizer.state[name]
        st.step += 1
        st.m, st.v = out["m"][name], out["v"][name]
        new[name] = out["raw"][name]
        dr.enable_grad(new[name])
    return new
