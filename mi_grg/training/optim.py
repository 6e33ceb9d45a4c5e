"""Adam with explicit, inspectable state (gsplat style) and 3DGS's log-linear lr decay.

One *group* per raw Gaussian parameter; the group names are the keys of
``Gaussians.to_raw()`` so that ``Adam.step(raw)`` works on that dict directly:

    ========================  =======  ===============================================
    group                     lr0      parameter (see ``mi_grg.core.gaussians``)
    ========================  =======  ===============================================
    ``positions``             2e-4     centres, mi.Point3f [N, 3] (length units)
    ``raw_densities``         1e-2     softplus^-1(density), mi.Float [N]
    ``raw_scales``            5e-3     log(scale), mi.Vector3f [N, 3]
    ``raw_rotations``         1e-3     unnormalised quaternion (w, x, y, z), mi.Vector4f
    ========================  =======  ===============================================

The rates are the GR-Gaussian paper's (Sec. 4.1.2) = R2-Gaussian's defaults, valid in
R2-Gaussian's normalised units (volume in [-1, 1]^3, i.e. after ``Geometry.scaled`` by
``scene_scale``). Each rate decays log-linearly to ``final_ratio`` (10 %) of its initial
value over ``max_steps`` steps and stays there (3DGS/R2-Gaussian ``get_expon_lr_func``):

    lr(t) = lr0 * final_ratio ** (clip(t, 0, max_steps) / max_steps)

or, with ``anneal=True``, goes on decaying past ``max_steps`` at the same log rate
(``final_ratio`` per ``max_steps`` steps): a run longer than its schedule converges
instead of going on at the final rate (``Schedule.horizon`` of the training config).

``rehorizon(at, max_steps)`` moves the end of the decay during a run (a run planned to a
time budget, mi_grg.training.budget): from step ``at`` on, the exponent goes on from its
value there and reaches 1 at the new ``max_steps``, so the rate never jumps. It may be
called again at later steps (each call adds a knot; the exponent is piecewise linear).

The update is PyTorch's Adam (no weight decay, no amsgrad), which R2-Gaussian uses:

    m <- b1 m + (1 - b1) g,   v <- b2 v + (1 - b2) g^2,   t <- t + 1
    p <- p - lr(t) / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)

``eps`` defaults to 1e-15 as in 3DGS and R2-Gaussian (``torch.optim.Adam(..., eps=1e-15)``):
with such a tiny eps a parameter whose gradient has always been exactly zero still gets
m = v = 0 and no update (0 / eps = 0), while small but nonzero gradients are not damped.
PyTorch's own default is 1e-8; pass ``eps=1e-8`` for that.

State per group: ``m``, ``v`` (Dr.Jit arrays of the parameter's type and width) and the
step count ``t``. Densification changes the number of Gaussians; ``remap`` / ``gather`` /
``extend`` perform the matching surgery on every group at once (survivors keep their
moments bit-exactly, new rows get zeros). The step count is NOT reset by surgery (as in
PyTorch/R2-Gaussian, where the state's ``step`` survives ``torch.cat``), so new rows see
the group's current bias correction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

# The paper's initial learning rates (R2-Gaussian's normalised units).
DEFAULT_LR = {"positions": 2e-4, "raw_densities": 1e-2, "raw_scales": 5e-3,
              "raw_rotations": 1e-3}


class AdamError(ValueError):
    """Misuse of the optimiser (unknown group, width mismatch, missing gradient)."""


@dataclass
class GroupState:
    """Adam state of one group: first/second moments (parameter's type) and step count."""

    m: object
    v: object
    step: int = 0


class Adam:
    """Adam over named groups of Dr.Jit arrays, with explicit state and lr decay.

    Args:
        lr: {group: initial learning rate}; default ``DEFAULT_LR``. Only these groups may
            be passed to ``step``.
        betas: (b1, b2) moment decay rates.
        eps: added to the bias-corrected sqrt(v) (see the module docstring).
        max_steps: steps over which each lr decays to ``final_ratio`` of its initial
            value (R2-Gaussian: 30000 = its iteration count); afterwards constant.
        final_ratio: lr(max_steps) / lr0; 0.1 as in the paper.
        anneal: past ``max_steps`` the rate keeps decaying, by ``final_ratio`` every
            ``max_steps`` steps, instead of staying at ``final_ratio``.
        check_finite: if True, every step raises on NaN/Inf gradients (one host sync per
            group and step; off by default for speed).
    """

    def __init__(self, lr: dict | None = None, betas=(0.9, 0.999), eps: float = 1e-15,
                 max_steps: int = 30000, final_ratio: float = 0.1,
                 check_finite: bool = False, anneal: bool = False):
        lr = dict(DEFAULT_LR if lr is None else lr)
        for name, value in lr.items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise AdamError(f"lr[{name!r}] must be a finite number >= 0, got {value!r}")
        b1, b2 = (float(b) for b in betas)
        if not (0 <= b1 < 1 and 0 <= b2 < 1):
            raise AdamError(f"betas must lie in [0, 1), got {betas!r}")
        if not (math.isfinite(eps) and eps >= 0):
            raise AdamError(f"eps must be finite and >= 0, got {eps!r}")
        if int(max_steps) < 1:
            raise AdamError(f"max_steps must be >= 1, got {max_steps!r}")
        if not 0 < final_ratio <= 1:
            raise AdamError(f"final_ratio must lie in (0, 1], got {final_ratio!r}")
        self.lr0 = {k: float(v) for k, v in lr.items()}
        self.betas = (b1, b2)
        self.eps = float(eps)
        self.max_steps = int(max_steps)
        self.knots = []         # [(step, exponent)] where rehorizon() moved the decay's end
        self.final_ratio = float(final_ratio)
        self.anneal = bool(anneal)
        self.check_finite = bool(check_finite)
        self.state: dict[str, GroupState] = {}   # created on a group's first step

    @classmethod
    def from_train_config(cls, cfg, max_steps: int, anneal: bool = False) -> "Adam":
        """From a ``mi_grg.training.config.TrainConfig`` (lr_position, lr_density, lr_scale,
        lr_rotation, lr_final_ratio); ``max_steps``: the decay horizon (iterations)."""
        return cls(lr={"positions": cfg.optim.lr_position, "raw_densities": cfg.optim.lr_density,
                       "raw_scales": cfg.optim.lr_scale, "raw_rotations": cfg.optim.lr_rotation},
                   max_steps=max_steps, final_ratio=cfg.optim.lr_final_ratio, anneal=anneal)

    # ------------------------------------------------------------------ schedule
    @property
    def groups(self) -> tuple:
        return tuple(self.lr0)

    def lr(self, name: str, step: int | float) -> float:
        """Learning rate of group ``name`` at step ``step`` (1 = the first update)."""
        self._check_name(name)
        return self.lr0[name] * self.final_ratio ** self._exponent(step)

    def _exponent(self, step: int | float) -> float:
        """How far the decay is at ``step``: 0 at the start, 1 at ``max_steps``; past it 1
        (or, annealing, 1 more every ``max_steps`` steps)."""
        if self.anneal and step > self.max_steps:
            return 1.0 + (float(step) - self.max_steps) / self.max_steps
        t = min(max(float(step), 0.0), float(self.max_steps))
        t0, e0 = 0.0, 0.0
        for t1, e1 in self.knots + [(self.max_steps, 1.0)]:
            if t <= t1:
                return e0 + (e1 - e0) * (t - t0) / (t1 - t0)
            t0, e0 = t1, e1
        return 1.0

    def rehorizon(self, at: int, max_steps: int) -> None:
        """From step ``at`` on, decay to ``final_ratio`` by step ``max_steps`` instead,
        continuing from the rate at ``at`` (unchanged before it; see the module docstring)."""
        at, max_steps = int(at), int(max_steps)
        if not 0 < at < max_steps:
            raise AdamError(f"rehorizon needs 0 < at < max_steps, got at={at}, "
                            f"max_steps={max_steps}")
        if self.knots and at <= self.knots[-1][0]:
            raise AdamError(f"rehorizon steps must increase: at={at} after a move at step "
                            f"{self.knots[-1][0]}")
        if at >= self.max_steps:
            raise AdamError(f"rehorizon at step {at}: the decay already ended at step "
                            f"{self.max_steps}")
        self.knots.append((at, self._exponent(at)))
        self.max_steps = max_steps

    def step_count(self, name: str) -> int:
        self._check_name(name)
        return self.state[name].step if name in self.state else 0

    # ------------------------------------------------------------------ update
    def step(self, params: dict, grads: dict | None = None, iteration: int | None = None) -> dict:
        """One Adam update of every group in ``params``.

        Args:
            params: {group: Dr.Jit array}. Groups not given are left untouched (their
                step count does not advance).
            grads: {group: gradient array of the same type/width}; default: ``dr.grad`` of
                each parameter (which then must have gradients enabled).
            iteration: schedule position for the lr; default: each group's own step count
                after this update (1 on the first call), which matches R2-Gaussian's
                ``update_learning_rate(iteration)`` with iterations counted from 1.

        Returns a NEW dict {group: updated array}, detached and with gradients enabled, so
        that it can feed the next forward pass. The inputs are not modified.
        """
        unknown = sorted(set(params) - set(self.lr0))
        if unknown:
            raise AdamError(f"unknown parameter group(s) {unknown}; known: {sorted(self.lr0)}")
        gs = {}
        for name, p in params.items():
            if grads is not None:
                if name not in grads:
                    raise AdamError(f"grads has no entry for group {name!r}")
                g = grads[name]
                if type(g) is not type(p):
                    g = type(p)(g)
            else:
                if not dr.grad_enabled(p):
                    raise AdamError(f"parameter {name!r} has no gradient: enable it with "
                                    "dr.enable_grad before the forward pass, or pass grads=")
                g = dr.grad(p)
            g = dr.detach(g)
            n = dr.width(p)
            if dr.width(g) != n:
                raise AdamError(f"gradient of {name!r} has width {dr.width(g)}, parameter {n}")
            st = self.state.get(name)
            if st is not None and dr.width(st.m) != n:
                raise AdamError(
                    f"group {name!r}: parameter has {n} rows but the Adam state has "
                    f"{dr.width(st.m)}; apply the same remap/gather/extend to the optimiser")
            gs[name] = g
        # Every group's gradient in one kernel: evaluated group by group, each would re-run
        # the derivative chain the groups share (the projector's record parameters).
        dr.eval(*gs.values())
        if self.check_finite:
            finite = {name: dr.all(dr.isfinite(g), axis=None) for name, g in gs.items()}
            dr.eval(*finite.values())
            for name, ok in finite.items():
                if not bool(ok):
                    raise AdamError(f"gradient of {name!r} contains NaN or Inf")
        # Checked above for every group first: an error leaves the whole state unchanged.
        out = {}
        for name, p in params.items():
            st = self.group_state(name, p)
            st.step += 1
            # Step-dependent scalars are opaque: as literals they would change the kernel
            # (and force a recompilation) at every step.
            step_size, inv_bc2 = (dr.opaque(mi.Float, x) for x in
                                  self.step_scalars(name, st.step, iteration))
            new, st.m, st.v = adam_update(p, gs[name], st.m, st.v, self.betas, self.eps,
                                          step_size, inv_bc2)
            dr.enable_grad(new)
            # one kernel per group: one kernel for all groups (42 streams) was 1.3x slower
            dr.eval(new, st.m, st.v)
            out[name] = new
        return out

    def recorded_inputs(self, params: dict):
        """Adam's inputs of a recorded step (``mi_grg.training.step.recorded_step``) for
        ``params``: the moments and this update's opaque scalars, or None where the update
        stays traced (the per-step finite check reads the host; an unknown group or a
        state of another width lets ``step`` raise its error)."""
        n = {dr.width(p) for p in params.values()}
        if self.check_finite or set(params) - set(self.lr0) or len(n) != 1:
            return None
        states = {name: self.group_state(name, p) for name, p in params.items()}
        if any(dr.width(st.m) not in n for st in states.values()):
            return None
        scalars = {name: self.step_scalars(name, st.step + 1) for name, st in states.items()}
        return {"m": {k: st.m for k, st in states.items()},
                "v": {k: st.v for k, st in states.items()},
                "step_size": {k: dr.opaque(mi.Float, a) for k, (a, _) in scalars.items()},
                "inv_bc2": {k: dr.opaque(mi.Float, b) for k, (_, b) in scalars.items()}}

    def apply(self, new: dict, m: dict, v: dict) -> dict:
        """Take one update computed elsewhere (a recorded step's, from
        ``recorded_inputs``): each group's step count advances and its moments become
        ``m``, ``v``. Returns the new parameters, gradients enabled (as ``step``)."""
        out = {}
        for name, p in new.items():
            st = self.state[name]
            st.step += 1
            st.m, st.v = m[name], v[name]
            out[name] = p
            dr.enable_grad(p)
        return out

    def group_state(self, name: str, p) -> GroupState:
        """Group ``name``'s state, created (zero moments like ``p``) on its first step."""
        st = self.state.get(name)
        if st is None:
            n = dr.width(p)
            st = GroupState(m=dr.zeros(type(p), n), v=dr.zeros(type(p), n))
            self.state[name] = st
        return st

    def step_scalars(self, name: str, t: int, iteration: int | None = None) -> tuple:
        """(lr / (1 - b1^t), 1 / sqrt(1 - b2^t)) of group ``name``'s t-th update (the lr at
        ``iteration`` if given, else at t)."""
        b1, b2 = self.betas
        lr = self.lr(name, t if iteration is None else iteration)
        return lr / (1.0 - b1 ** t), 1.0 / math.sqrt(1.0 - b2 ** t)

    # ------------------------------------------------------------------ state surgery
    def width(self) -> int | None:
        """Common row count of every group's state (None before the first step)."""
        widths = {dr.width(st.m) for st in self.state.values()}
        if not widths:
            return None
        if len(widths) > 1:
            raise AdamError(f"groups have different widths {sorted(widths)}: surgery needs "
                            "one row per Gaussian in every group")
        return widths.pop()

    def remap(self, src, keep_moments=None) -> None:
        """New state row r takes old row ``src[r]``'s moments where ``keep_moments[r]``
        (default everywhere) and zeros elsewhere, in every group; step counts unchanged.

        ``src`` is an mi.UInt32 of the new width; entries where ``keep_moments`` is False
        are ignored (may be anything).
        """
        n = self.width()
        if n is None:
            return
        src = mi.UInt32(src)
        if keep_moments is None:
            keep_moments = dr.full(mi.Bool, True, dr.width(src))
        keep_moments = mi.Bool(keep_moments)
        if dr.width(keep_moments) != dr.width(src):
            raise AdamError("keep_moments must have the width of src")
        # n opaque: a literal would make a new kernel at every densification
        if dr.width(src) and bool(dr.any(keep_moments & (src >= dr.opaque(mi.UInt32, n)), axis=None)):
            raise AdamError(f"remap index out of range (state has {n} rows)")
        for st in self.state.values():
            st.m = dr.gather(type(st.m), st.m, src, keep_moments)
            st.v = dr.gather(type(st.v), st.v, src, keep_moments)
            dr.eval(st.m, st.v)

    def gather(self, indices) -> None:
        """Keep the state rows ``indices`` (mi.UInt32), in that order, in every group."""
        self.remap(indices)

    def extend(self, n_new: int) -> None:
        """Append ``n_new`` rows of zero moments to every group."""
        n = self.width()
        if n is None:
            return
        if int(n_new) < 0:
            raise AdamError(f"n_new must be >= 0, got {n_new}")
        rows = dr.arange(mi.UInt32, n + int(n_new))
        self.remap(rows, rows < n)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """NumPy copy of the whole state: {group: {"m": [N, C], "v": [N, C], "step": int}}."""
        return {k: {"m": _to_rows(st.m), "v": _to_rows(st.v), "step": st.step}
                for k, st in self.state.items()}

    def load_state_dict(self, state: dict, like: dict) -> None:
        """Restore ``state_dict()`` output; ``like`` gives each group's array type
        (e.g. the raw parameter dict)."""
        for k, s in state.items():
            self._check_name(k)
            tp = type(like[k])
            self.state[k] = GroupState(m=_from_rows(tp, s["m"]), v=_from_rows(tp, s["v"]),
                                       step=int(s["step"]))

    def _check_name(self, name):
        if name not in self.lr0:
            raise AdamError(f"unknown parameter group {name!r}; known: {sorted(self.lr0)}")


def adam_update(p, g, m, v, betas, eps: float, step_size, inv_bc2):
    """One group's Adam update: (new parameter, detached; m; v) from the gradient ``g``,
    the moments and the step's opaque scalars (``Adam.step_scalars``). ``Adam.step`` and
    the recorded training step (mi_grg.training.step.recorded_step) both use it."""
    b1, b2 = betas
    m = type(p)(dr.fma(m, b1, (1.0 - b1) * g))
    v = type(p)(dr.fma(v, b2, (1.0 - b2) * dr.square(g)))
    denom = dr.sqrt(v) * inv_bc2 + eps
    return type(p)(dr.detach(p) - step_size * m / denom), m, v


def _to_rows(x) -> np.ndarray:
    """[N, C] float32 copy of a Dr.Jit array (C = 1 for scalar arrays)."""
    if dr.depth_v(x) == 1:
        return np.asarray(x, dtype=np.float32).reshape(-1, 1)
    return np.stack([np.asarray(c, dtype=np.float32) for c in x], axis=-1)


def _from_rows(tp, rows):
    rows = np.asarray(rows, dtype=np.float32)
    # copied, not mapped onto the caller's NumPy memory (mi_grg.training.checkpoint)
    if dr.depth_v(tp) == 1:
        return tp(np.array(rows.reshape(-1)))
    return tp(*[mi.Float(rows[:, c]) for c in range(rows.shape[1])])
