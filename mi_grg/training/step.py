"""One training iteration's loss and gradients, written once.

    Gaussians.from_raw -> the projection of one view (with ``means2d``, whose gradient is
    the densification statistic) -> L1 (or RMS: ``data_loss``) + lambda_ssim D-SSIM -> + TV
    on a voxelised block (every ``tv_every``-th iteration, weighted ``tv_every`` x) -> + the
    graph Laplacian -> backward -> every gradient in one kernel.

``loss_and_grads(cfg, inputs)`` is that body. The trainer's traced step calls it directly;
the recorded step (``mi_grg.training.recording``) records ``recorded_step``, the same call
followed by the densification statistics and Adam, with the data-dependent sizes as
capacities (``StepInputs.capacity``: the mode is switched by the inputs, not by another
body). The refit after an early stop is the same call with TV, the Laplacian and the
screen-space gradient off (``StepConfig.refit``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians

# The paper's Laplacian weight (8e-4) goes with its raw double sum over M = 50k Gaussians;
# we scale the raw sum by REFERENCE_N / N so the same weight means the same at any N.
REFERENCE_N = 50000
# Floats of a per-view scan's detector-value input (6 used; padded, as a width-1 input's
# alignment would key a recording)
DETECTOR_PAD = 16


def laplacian_weight(lambda_lap: float, n: int) -> "mi.Float":
    """The Laplacian term's weight at N Gaussians, lambda_lap x REFERENCE_N / N, as an
    opaque scalar: as a literal it changed with every densification and made new kernels."""
    return dr.opaque(mi.Float, lambda_lap * (REFERENCE_N / max(n, 1)))


def evaluate_gradients(raw: dict, *extra) -> None:
    """Every raw parameter's gradient (and ``extra`` arrays, such as the means2d gradient)
    in one kernel, after the backward pass. They share the derivative chain from the
    projector's record parameters to the raw parameters; read one by one (the
    densification statistics, then Adam's groups), each re-ran that chain."""
    dr.eval(*extra, *(dr.grad(v) for v in raw.values()))


def tv_weight(losses) -> float:
    """The TV term's weight on the iterations that have it: lambda_tv x tv_every (the term
    runs on every ``tv_every``-th iteration only, so the mean weight stays lambda_tv)."""
    return losses.lambda_tv * losses.tv_every


def tv_block(losses, geometry) -> tuple:
    """The TV block's size [x, y, z]: ``tv_block`` voxels, at most the grid."""
    return tuple(int(x) for x in np.minimum(losses.tv_block, np.asarray(geometry.nVoxel)))


def screen_gradient_norm(grad2d, nv: int, nu: int):
    """|dL/d means2d| in NDC units from the projector's per-pixel gradient: R2-Gaussian's
    threshold (tau_pos) is per NDC unit, ndc = 2 pixel / n - 1, so d/d(ndc) = (n/2) d/d(pixel)."""
    return dr.norm(mi.Vector2f(grad2d.x * (nu / 2.0), grad2d.y * (nv / 2.0)))


@dataclass(frozen=True)
class TVTerm:
    """The TV term of an iteration that has one: weight, block size [x, y, z], support."""
    weight: float
    block: tuple
    support: float


@dataclass(frozen=True)
class StepConfig:
    """The iteration's constants: the scan, the projector's support, the loss weights (TV:
    None for none; ``lambda_lap`` 0: no Laplacian) and whether the screen-space gradient is
    wanted (the densification statistics)."""
    geometry: object
    extent: float
    lambda_ssim: float
    tv: TVTerm | None = None
    lambda_lap: float = 0.0
    screen_gradient: bool = True
    data_loss: str = "l1"

    @classmethod
    def from_train_config(cls, cfg, geometry, extent: float, tv_extent: float) -> "StepConfig":
        tv = TVTerm(tv_weight(cfg.losses), tv_block(cfg.losses, geometry), float(tv_extent))
        return cls(geometry, float(extent), cfg.losses.lambda_ssim, tv,
                   float(cfg.graph.lambda_lap), data_loss=cfg.losses.data_loss)

    def refit(self) -> "StepConfig":
        """The refit's iteration: the projection loss alone."""
        return dataclasses.replace(self, tv=None, lambda_lap=0.0, screen_gradient=False)

    @property
    def detector(self) -> tuple:
        """(nv, nu)"""
        return tuple(int(x) for x in self.geometry.nDetector)

    @cached_property
    def view0(self):
        """The first view's frames: the detector constants, the same for every view of a
        circular scan (a per-view scan's differing ones come with each view's inputs,
        ``view_arrays``)."""
        from mi_grg.core.view_frames import view_frames
        first = view_frames(self.geometry.with_angles(self.geometry.angles[:1]))
        # a skewed scan's kernels carry the shear in every view, view 0's too
        return dataclasses.replace(first, skewed=self._frames.skewed)

    @cached_property
    def shared(self) -> bool:
        """Whether every view has the same detector values (``ViewFrames.shared``)."""
        return self._frames.shared

    @cached_property
    def _frames(self):
        from mi_grg.core.view_frames import view_frames
        return view_frames(self.geometry)


@dataclass
class StepInputs:
    """What one iteration reads (a Dr.Jit PyTree): the raw parameters (gradients
    enabled), the view's frame arrays (``view_arrays``), its target image [v, u], the
    graph-field density multiplier (None: plain field), the graph and the Laplacian's
    weight (None: no Laplacian), the TV block's corner (3 ints, or 3 x mi.Int32 when
    recorded; None: no TV) and the capacities (None: traced, the sizes read on the host;
    else ((rows, near records), (cols, slices) or None), a recording's lane counts)."""
    raw: dict
    view: dict
    target: object
    density_scale: object = None
    graph: object = None
    lap_weight: object = None
    tv_start: object = None
    capacity: object = None


@dataclass
class StepOutputs:
    """The loss (mi.Float [1], detached), every raw parameter's gradient, the screen-space
    gradient norm per Gaussian (NDC units; None when not wanted) and, when recorded, the
    lane counts the capacities had to hold ([rows, near, cols, slices], mi.UInt32 [1])."""
    loss: object
    grads: dict
    gnorm: object = None
    counts: object = None


def owned(x):
    """A copy of ``x`` in Dr.Jit's own memory: arrays made from NumPy may map host memory,
    whose alignment (part of a recording's key) varies from array to array."""
    y = dr.empty(type(x), dr.width(x))
    dr.scatter(y, x, dr.arange(mi.UInt32, dr.width(x)))
    dr.eval(y)
    return y


def view_arrays(geometry, view: int, shared: bool | None = None) -> dict:
    """The frame arrays of one view as ``project_dr`` builds them for that view alone
    ({"e": 3 x 3 mi.Float, "o": 3 mi.Float}), in Dr.Jit's own memory (``owned``). An input
    of the step, so that one recording serves every view. (Where the detector constants
    are the same for every view (``ViewFrames.shared``, every circular scan; None: read
    off ``geometry``) they are built inside, as width-1 inputs would make a recording
    depend on their addresses' alignment; a per-view scan's own are a padded input
    "det", ``DetectorConstants.override``.)"""
    from mi_grg.core.projector_records import ViewFrameArrays
    from mi_grg.core.view_frames import view_frames
    if shared is None:
        shared = view_frames(geometry).shared
    fr = view_frames(geometry.with_angles(geometry.angles[view:view + 1]))
    fa = ViewFrameArrays(fr)
    out = {"e": [[owned(c) for c in axis] for axis in fa.e], "o": [owned(c) for c in fa.o]}
    if not shared:
        vals = np.zeros(DETECTOR_PAD, np.float32)
        h, a_u, a_v, du, dv, sk = fr.detector_values(0)
        vals[:7] = (h, h * h, a_u, a_v, du, dv, sk)   # h^2 rounded once, as DetectorConstants
        out["det"] = owned(mi.Float(vals))
    return out


def loss_and_grads(cfg: StepConfig, inputs: StepInputs) -> StepOutputs:
    """The iteration's loss and its gradients (see the module docstring)."""
    from mi_grg.core.projector import prepare, project_prepared
    from mi_grg.training.losses import projection_loss
    nv, nu = cfg.detector
    raw = inputs.raw
    g = Gaussians.from_raw(raw)
    means2d = None
    if cfg.screen_gradient:
        means2d = dr.zeros(mi.Vector2f, len(g))
        dr.enable_grad(means2d)
    caps = inputs.capacity
    if caps is None:     # traced: project_dr's input checks (host reads)
        from mi_grg.core.projector_inputs import validate
        validate(g, len(g), inputs.density_scale, means2d, 1)
    setup = prepare(cfg.geometry, len(g), cfg.extent, inputs.view, cfg.view0,
                    rows=None if caps is None else caps[0])
    img = project_prepared(setup, g, inputs.density_scale, means2d)
    loss = projection_loss(mi.TensorXf(img, (nv, nu)), inputs.target, cfg.lambda_ssim,
                           cfg.data_loss)
    pairs = None
    if inputs.tv_start is not None:
        tv, pairs = _tv_term(cfg, inputs, g)
        loss = loss + tv
    if cfg.lambda_lap > 0 and inputs.lap_weight is not None:
        from mi_grg.training.graph import laplacian_loss
        loss = loss + inputs.lap_weight * laplacian_loss(inputs.graph, g.densities,
                                                         normalise=False)
    dr.backward(loss)
    loss = dr.detach(loss)
    grads = {k: dr.grad(v) for k, v in raw.items()}
    gnorm = grad2d = None
    if means2d is not None:
        grad2d = dr.grad(means2d)
    if caps is None:
        evaluate_gradients(raw, *([] if grad2d is None else [grad2d]), loss)
    if grad2d is not None:
        gnorm = screen_gradient_norm(grad2d, nv, nu)
    counts = None
    if caps is not None:
        U = mi.UInt32
        counts = [setup.caps.rows_total, setup.caps.near_count]
        counts += ([pairs.cols_total, pairs.slices_total] if pairs is not None
                   else [dr.zeros(U, 1), dr.zeros(U, 1)])
        counts = [U(c) for c in counts]
        dr.eval(grads, gnorm)
    return StepOutputs(loss, grads, gnorm, counts)


class PairCapacity:
    """The TV block's column and slice lanes (a recording's); the plan leaves the totals
    it needed."""

    def __init__(self, cols: int, slices: int):
        self.cols, self.slices = int(cols), int(slices)
        self.cols_total = self.slices_total = None


def _tv_term(cfg: StepConfig, inputs: StepInputs, g: Gaussians):
    """(weighted TV of the block at ``inputs.tv_start``, its pair capacity or None)."""
    from mi_grg.core.voxelizer import voxelize_block_capacity, voxelize_dr
    from mi_grg.training.losses import tv_3d
    tv = cfg.tv
    if inputs.capacity is None:
        vol = voxelize_dr(g, cfg.geometry, block=(list(inputs.tv_start), list(tv.block)),
                          extent=tv.support, density_scale=inputs.density_scale)
        return tv.weight * tv_3d(vol), None
    pairs = PairCapacity(*inputs.capacity[1])
    vol = voxelize_block_capacity(g, cfg.geometry, inputs.tv_start, tv.block, tv.support,
                                  inputs.density_scale, pairs)
    return tv.weight * tv_3d(vol), pairs


def recorded_step(holder, inputs: StepInputs, update, key: tuple) -> dict:
    """What a recording records (``holder.cfg``: the StepConfig, in a plain object that
    the frozen function keys by identity): ``loss_and_grads`` on a detached copy of the
    parameters, then, when ``update`` is given (``Adam.recorded_inputs``,
    ``PGADensifier.recorded_inputs``), the densification statistics and Adam with the
    same functions their traced methods use. ``key``: the recording's key (sizes and
    capacities; its last entry Adam's (betas, eps))."""
    from mi_grg.training.densify import add_one_view
    from mi_grg.training.optim import adam_update
    raw = {}
    for k, v in inputs.raw.items():
        raw[k] = type(v)(dr.detach(v))
        dr.enable_grad(raw[k])
    out = loss_and_grads(holder.cfg, dataclasses.replace(inputs, raw=raw))
    res = {"loss": out.loss, "grads": out.grads, "gnorm": out.gnorm, "counts": out.counts}
    if update is not None:
        g = dr.detach(out.gnorm)
        res["stats"] = add_one_view(update["stats"]["grad_accum"],
                                    update["stats"]["view_count"], g, g > 0)
        betas, eps = key[-1]
        adam = update["adam"]
        res["raw"], res["m"], res["v"] = {}, {}, {}
        for name, p in inputs.raw.items():
            new, m, v = adam_update(p, dr.detach(out.grads[name]), adam["m"][name],
                                    adam["v"][name], betas, eps, adam["step_size"][name],
                                    adam["inv_bc2"][name])
            dr.eval(new, m, v)       # one kernel per group, as Adam.step
            res["raw"][name], res["m"][name], res["v"][name] = new, m, v
    dr.eval(res)
    return res
