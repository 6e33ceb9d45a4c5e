"""A training iteration recorded once with Dr.Jit's frozen functions (``dr.freeze``) and
replayed: no Python tracing, no host read inside it.

What is recorded: Gaussians.from_raw -> the projection of one view (with means2d) -> L1 +
D-SSIM -> the graph Laplacian -> backward -> the raw gradients and the densification
statistics' per-Gaussian gradient norms. What stays outside (``Trainer._step``): the draws,
the statistics' accumulation, the loss read (the one host synchronisation of an
iteration, as on the traced path), Adam, and the iterations with a TV block, which run
traced (the voxelizer plans its pairs on the host).

The traced projector reads data-dependent sizes on the host (the footprint rows of the
regular records, the near-source records); a recording cannot. Here they are capacities
fixed when the step is recorded (``RowCapacity``): ``rows`` (record, row) lanes, the rows
past the last record's masked, and no near-source lanes. The counts come back with the
result; a count past its capacity (more rows, or a near-source record) discards the
result, the iteration runs traced, the capacity grows and the next call records anew.
Each kind of event is said once (``notes``). A recording is keyed by the Gaussian count,
the graph's sizes and the capacity: densification and graph rebuilds record anew.

Exact: the recorded step evaluates the same expressions as the traced one; only the lane
count differs (masked lanes add zeros). See docs/frozen_step.md for the host reads of the
traced step and where each went.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.projector import _ProjectionSetup, _ProjectOp
from mi_grg.core.projector_chunks import RowCapacity
from mi_grg.core.projector_records import DetectorConstants, ViewFrameArrays
from mi_grg.core.view_frames import view_frames

# Headroom of the row capacity over the most rows per Gaussian seen so far (the rows of
# a view vary with the view), and its granularity (so that small changes keep a recording)
ROW_HEADROOM = 1.25
ROW_QUANTUM = 4096
INITIAL_ROWS_PER_GAUSSIAN = 4.0


class _Static:
    """The step's Python constants (not a PyTree: the frozen function hashes it by id)."""

    def __init__(self, geometry, extent, lambda_ssim):
        self.geometry, self.extent, self.lambda_ssim = geometry, float(extent), lambda_ssim
        self.frames = view_frames(geometry)
        self.nv, self.nu = geometry.nDetector


def _frame_arrays(frames) -> dict:
    """Every view's frame vectors (ViewFrameArrays) as a PyTree, an input of the step."""
    fa = ViewFrameArrays(frames)
    dr.eval(fa.e, fa.o)
    return {"e": fa.e, "o": fa.o}


def _setup(static: _Static, inputs: dict, n: int, rows: int) -> _ProjectionSetup:
    """project_dr's setup of view ``inputs["view"]`` with a row capacity: the frames of
    every view come in as an input, and project_dr's input checks (host reads) are left
    out (the loss read and Adam's gradient check stay outside)."""
    fa = object.__new__(ViewFrameArrays)
    fa.e, fa.o = inputs["frames"]["e"], inputs["frames"]["o"]
    det = DetectorConstants(static.frames, static.geometry, static.extent)
    setup = _ProjectionSetup(static.geometry, fa, det, n, 1)
    setup.caps = RowCapacity(inputs["view"], rows)
    return setup


def _step_body(static: _Static, inputs: dict, key: tuple) -> dict:
    """The recorded iteration (``key`` = (N, row capacity, graph sizes) keys recordings)."""
    from mi_grg.training.graph import laplacian_loss
    from mi_grg.training.losses import projection_loss
    raw = {}
    for k, v in inputs["raw"].items():
        raw[k] = type(v)(dr.detach(v))
        dr.enable_grad(raw[k])
    g = Gaussians.from_raw(raw)
    n = len(g)
    means2d = dr.zeros(mi.Vector2f, n)
    dr.enable_grad(means2d)
    setup = _setup(static, inputs, len(g), key[1])
    img = dr.custom(_ProjectOp, g.positions, g.scales, g.rotations, g.densities,
                    inputs["ds"], means2d, setup)
    pred = mi.TensorXf(img, (static.nv, static.nu))
    loss = projection_loss(pred, inputs["target"], static.lambda_ssim)
    if inputs["graph"] is not None:
        lap = laplacian_loss(inputs["graph"], g.densities, normalise=False)
        loss = loss + inputs["lap_weight"] * lap
    dr.backward(loss)
    grad2d = dr.grad(means2d)
    gnorm = dr.norm(mi.Vector2f(grad2d.x * (static.nu / 2.0), grad2d.y * (static.nv / 2.0)))
    grads = {k: dr.grad(v) for k, v in raw.items()}
    caps = setup.caps
    out = {"loss": dr.detach(loss), "grads": grads, "gnorm": gnorm,
           "counts": [mi.UInt32(caps.rows_total), mi.UInt32(caps.near_count)]}
    dr.eval(out)
    return out


class FrozenStep:
    """The recorded training iteration of a ``Trainer`` (see the module docstring).

    ``iteration(trainer, it, raw, view)`` runs one iteration without TV block and returns
    (new raw, loss value), or None when this iteration must run traced (the caller then
    runs its own step: nothing of the recorded run is kept)."""

    def __init__(self, geometry, extent, lambda_ssim, log=print):
        self.static = _Static(geometry, extent, lambda_ssim)
        self.frames = _frame_arrays(self.static.frames)
        self.fn = dr.freeze(_step_body, limit=1, warn_after=1 << 30)
        self.rows_per_gaussian = INITIAL_ROWS_PER_GAUSSIAN
        self.capacity = None        # (N, rows) of the current recording
        self.log, self.said = log, set()
        self.replays = self.fallbacks = 0

    def note(self, kind: str, text: str) -> None:
        """Say ``text`` once per kind of event (overflows are expected after growth)."""
        if kind not in self.said:
            self.said.add(kind)
            self.log(f"frozen step: {text}")

    def rows_capacity(self, n: int) -> int:
        """Row lanes for N Gaussians: the most rows per Gaussian seen, with headroom."""
        if self.capacity is not None and self.capacity[0] == n:
            return self.capacity[1]
        rows = math.ceil(self.rows_per_gaussian * ROW_HEADROOM * max(n, 1) / ROW_QUANTUM)
        self.capacity = (n, rows * ROW_QUANTUM)
        return self.capacity[1]

    def run(self, raw: dict, view: int, target, graph, density_scale, lap_weight):
        """The recorded computation on this state: {loss, grads, gnorm, counts} (lazy
        outputs of the replay) and the key it ran under."""
        n = dr.width(raw["raw_densities"])
        if graph is not None:
            from mi_grg.training.graph import neighbour_table
            neighbour_table(graph)       # its host read, once per graph, outside
        key = (n, self.rows_capacity(n), None if graph is None else
               (graph.n, graph.num_edges, graph.table[0] if graph.table else None))
        inputs = {"raw": {k: dr.detach(v) for k, v in raw.items()},
                  "view": dr.opaque(mi.UInt32, view), "target": target,
                  "frames": self.frames, "ds": density_scale,
                  "graph": graph, "lap_weight": lap_weight if graph is not None else None}
        return self.fn(self.static, inputs, key), key

    def check(self, out: dict, key: tuple) -> float | None:
        """The loss value, or None (the result is incomplete: the capacity grows, said once)."""
        vals = np.concatenate([np.asarray(out["loss"], np.float64).reshape(-1)[:1]]
                              + [np.asarray(c, np.float64).reshape(-1)[:1]
                                 for c in out["counts"]])
        loss, rows, near = float(vals[0]), int(vals[1]), int(vals[2])
        n, cap = key[0], key[1]
        self.rows_per_gaussian = max(self.rows_per_gaussian, rows / max(n, 1))
        if near:
            self.note("near", "a Gaussian near the source needs the whole-detector lanes, "
                      "which a recording does not hold: such iterations run traced")
            return None
        if rows > cap:
            self.capacity = None        # the next call records with room for these rows
            self.note("rows", f"{rows} footprint rows exceed the recorded capacity {cap}: "
                      "this iteration runs traced, the next records a larger capacity")
            return None
        return loss

    def iteration(self, trainer, it: int, raw: dict, view: int, laplacian_weight):
        """One iteration of ``trainer`` (no TV block this iteration): (new raw, loss
        value), or None (run it traced). ``laplacian_weight(lambda_lap, n)``: the
        trainer's weight of the Laplacian term."""
        from mi_grg.core.projector import RECORDS_PER_CHUNK
        n = dr.width(raw["raw_densities"])
        if n == 0 or n > RECORDS_PER_CHUNK:
            self.note("chunks", f"{n} Gaussians do not fit one projector chunk: traced")
            self.fallbacks += 1
            return None
        lap_weight = None
        if trainer.cfg.lambda_lap > 0 and trainer.graph is not None:
            lap_weight = laplacian_weight(trainer.cfg.lambda_lap, n)
        graph = trainer.graph if lap_weight is not None else None
        out, key = self.run(raw, view, trainer.targets[view], graph,
                            trainer._density_scale, lap_weight)
        loss_value = self.check(out, key)
        if loss_value is None:
            self.fallbacks += 1
            return None
        self.replays += 1
        trainer.densifier.accumulate(out["gnorm"], visible=out["gnorm"] > 0)
        if not math.isfinite(loss_value):
            raise FloatingPointError(f"loss is {loss_value} at iteration {it}")
        return trainer.optimizer.step(raw, grads=out["grads"]), loss_value
