"""PGA densification (GR-Gaussian Sec. 3.3.2) as a strategy object with explicit state.

R2-Gaussian's adaptive density control (``densify_and_prune``), with the paper's graph
term added to the densification gradient. Every ``interval`` iterations in the window
``start < iteration < stop`` (R2-Gaussian's exclusive bounds):

1. Augmented gradient per Gaussian:
       g_i = (1 / N_i) sum_v ||dL_v / dmu2d_{i,v}||  +  lambda_g * mean_{j in N(i)} |rho_i - rho_j|
   The first term is R2-Gaussian's averaged detector-plane gradient norm, accumulated by
   ``accumulate`` over the N_i views in which Gaussian i was visible since the last
   densification (0 if never visible). The second is PGA's graph term, computed by the
   caller (``mi_grg.training.graph.mean_abs_density_difference``) on the current graph; it is
   added once to the view average, which equals the paper's per-view sum
   (Eq. 16) averaged over views. ``use_pga=False`` drops it (R2-Gaussian).
2. Candidates: g_i >= tau_pos (``densify_grad_threshold``, default 5e-5, R2-Gaussian's
   ``densify_grad_threshold``): it assumes the 3DGS/R2 convention for mu2d, i.e. the
   gradient w.r.t. the projected centre in NDC-like detector coordinates of range [-1, 1]
   (d/d ndc = n/2 d/d pixel). The projector's gradient must be expressed in the same
   unit for the default to mean the same thing.
3. Cap: each candidate adds exactly one Gaussian (a clone adds a copy; a split replaces
   the parent by two children). If N + #candidates > max_count (the window's cap), only the
   max(max_count - N, 0) candidates with the largest g_i are densified (ties: lower index
   first). R2-Gaussian instead skips densification entirely once N >= max_count; ours is
   the same at N >= max_count and degrades gracefully below it.
4. Clone (max scale <= clone_scale_fraction x volume size, volume size = max bbox edge =
   max(sVoxel); R2's ``densify_scale_threshold`` 0.1): the Gaussian and an identical copy,
   each with HALF the physical density. Integrated mass
   rho (2 pi)^{3/2} s_x s_y s_z is preserved (up to float32 rounding of the softplus
   round trip).
5. Split (max scale above it): the parent is replaced by 2 children at positions drawn
   from the parent Gaussian (p + R (s * z), z ~ N(0, I)), scales s / 1.6 (R2's
   s / (0.8 N), N = 2), same rotation, each with HALF the parent's density. Their total
   mass is the parent's / 1.6^3 = / 4.096 -- NOT preserved (R2-Gaussian's bookkeeping,
   reproduced deliberately).
6. Prune (after densification, children included): density < min_density (1e-5, R2's
   ``density_min_threshold``), or centre outside the volume bbox enlarged by
   bbox_margin x its size on every side (0: R2-Gaussian's exact bbox), or non-finite.
7. Adam state: survivors keep their moments bit-exactly (a cloned original too, although
   its density halves, as in R2-Gaussian where the tensor is edited in place); clone
   copies and split children start from zero moments. Accumulators reset to zero.

``info["source"]`` (mi.UInt32 [n_after]) is the row each result row came from (itself, the
cloned original, or the split parent); the trainer uses it to carry the graph field's
density multiplier over a graph rebuild.

Row order of the result: surviving originals in their order, then clone copies, then the
first children of all split parents, then the second children (R2-Gaussian's order).
Physical <-> raw conversions go through ``Gaussians.from_raw`` / ``to_raw`` only; rows that
do not change keep their raw values bit-exactly. The split positions come from a PCG32
stream seeded by (seed, iteration): deterministic, identical on both variants.
The caller must rebuild its kNN graph after a densification step (the set changed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians, rotation_matrix
from mi_grg.training.config import Densification
from mi_grg.training.optim import Adam

RAW_KEYS = ("positions", "raw_scales", "raw_rotations", "raw_densities")


class DensifyError(ValueError):
    """Invalid densification input; the message names it."""


@dataclass
class DensifyWindow:
    """A run's densification window and cap (explicit state beside the settings): densify
    every ``interval`` iterations when start < iteration < stop, up to ``max_count``
    Gaussians. ``for_config``: the settings' own (unscaled) window and cap; a trainer
    scales them to its run (``mi_grg.training.schedule``) and a time budget may end the
    window earlier."""
    start: int = 500
    stop: int = 15000
    interval: int = 100
    max_count: int = 500_000

    @classmethod
    def for_config(cls, config: Densification) -> "DensifyWindow":
        return cls(config.densify_start, config.densify_stop, config.densify_interval,
                   config.max_gaussians)


def _check(config: Densification, window: DensifyWindow) -> None:
    """The settings the densifier uses, each error naming its field."""
    if window.interval < 1:
        raise DensifyError(f"interval must be >= 1, got {window.interval}")
    for name in ("densify_grad_threshold", "lambda_g", "clone_scale_fraction", "min_density",
                 "bbox_margin"):
        v = getattr(config, name)
        if not (math.isfinite(v) and v >= 0):
            raise DensifyError(f"{name} must be finite and >= 0, got {v}")
    if not (math.isfinite(config.split_scale_factor) and config.split_scale_factor > 0):
        raise DensifyError(f"split_scale_factor must be > 0, got {config.split_scale_factor}")
    if window.max_count < 1:
        raise DensifyError(f"max_count must be >= 1, got {window.max_count}")


def densify_iterations(start: int, stop: int, interval: int, last: int) -> range:
    """The iterations up to ``last`` that densify: the multiples of ``interval`` strictly
    between ``start`` and ``stop`` (the one rule; ``PGADensifier.is_densify_iteration``)."""
    return range(interval * (start // interval + 1), min(stop, last + 1), interval)


#: Densification met the field's demand where, over the last quarter of its window, the
#: count grew by less than this share ...
DEMAND_GROWTH = 0.05
#: ... and ended below this share of the window's cap (at the cap, candidates were cut).
DEMAND_CAP = 0.99


def demand(log: list, window: DensifyWindow) -> dict:
    """Whether densification met the field's demand, from a run's ``log`` (rows with
    "iteration" and "n_gaussians") and its ``window``: where the count still grew over the
    window's last quarter, or reached the cap, the field wanted more Gaussians than it got
    and does not resolve the object (docs/benchmarks.md, "The refinement's anchor").
    {"growth": the count's relative growth over the last quarter (of the part run),
    "cap_share": the count at the window's end over the cap, "met": bool}; a run that
    never densified (no row in the window) met it."""
    rows = [(int(r["iteration"]), int(r["n_gaussians"])) for r in log
            if "n_gaussians" in r and int(r["iteration"]) <= window.stop]
    if not rows or rows[-1][0] <= window.start:
        return {"growth": 0.0, "cap_share": None, "met": True}
    end_it, n_end = rows[-1]
    quarter = end_it - (end_it - window.start) / 4.0
    before = [n for it, n in rows if it <= quarter]
    n_q = before[-1] if before else rows[0][1]
    growth = n_end / max(n_q, 1) - 1.0
    cap_share = n_end / window.max_count
    return {"growth": growth, "cap_share": cap_share,
            "met": bool(growth < DEMAND_GROWTH and cap_share < DEMAND_CAP)}


def _seed_state(seed: int, iteration: int) -> int:
    """64-bit PCG32 initstate from (seed, iteration) (splitmix-style mixing)."""
    z = (int(seed) * 0x9E3779B97F4A7C15 + int(iteration) + 0x632BE59BD9B4E019) % (1 << 64)
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) % (1 << 64)
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) % (1 << 64)
    return z ^ (z >> 31)


def standard_normal3(n: int, seed: int, iteration: int) -> "mi.Vector3f":
    """n independent N(0, I_3) samples (Box-Muller on a PCG32 stream per row)."""
    rng = mi.PCG32(size=n, initstate=mi.UInt64(_seed_state(seed, iteration)),
                   initseq=dr.arange(mi.UInt64, n))
    u = [rng.next_float32() for _ in range(4)]
    # 1 - u lies in (0, 1]: the log is finite.
    r0 = dr.sqrt(-2.0 * dr.log(1.0 - u[0]))
    r1 = dr.sqrt(-2.0 * dr.log(1.0 - u[2]))
    s0, c0 = dr.sincos(2.0 * math.pi * u[1])
    s1, _ = dr.sincos(2.0 * math.pi * u[3])
    return mi.Vector3f(r0 * c0, r0 * s0, r1 * s1)


def _check_raw(raw: dict) -> int:
    missing = [k for k in RAW_KEYS if k not in raw]
    extra = [k for k in raw if k not in RAW_KEYS]
    if missing or extra:
        raise DensifyError(f"raw parameters must have exactly the keys {RAW_KEYS}; "
                           f"missing {missing}, unexpected {extra}")
    n = dr.width(raw["raw_densities"])
    for k in RAW_KEYS:
        if dr.width(raw[k]) != n:
            raise DensifyError(f"raw[{k!r}] has width {dr.width(raw[k])}, raw_densities {n}")
    return n


def _bbox(bbox) -> np.ndarray:
    b = np.asarray(bbox, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
        raise DensifyError(f"bbox must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with "
                           f"min < max, got {bbox!r}")
    return b


class _Rows:
    """The rows of a densification before pruning, [originals | clone copies | first
    children | second children] (m = n + nc + 2 ns), and each row's source Gaussian."""

    def __init__(self, n: int, clone, split):
        ci = dr.compress(clone)
        si = dr.compress(split)
        nc, ns = dr.width(ci), dr.width(si)
        self.nc, self.ns, self.m = nc, ns, n + nc + 2 * ns
        row = dr.arange(mi.UInt32, self.m)
        # The counts as opaque variables: as literals they made new kernels at each
        # densification (compiled every time, since they change every time)
        n_o, nnc_o = dr.opaque(mi.UInt32, n), dr.opaque(mi.UInt32, n + nc)
        self.is_orig = row < n_o
        self.is_clone = (row >= n_o) & (row < nnc_o)
        self.is_child = row >= nnc_o
        src = dr.select(self.is_orig, row, 0)
        if nc:
            src = dr.select(self.is_clone, dr.gather(mi.UInt32, ci, row - n_o, self.is_clone), src)
        if ns:
            k = (row - nnc_o) % dr.opaque(mi.UInt32, ns)
            src = dr.select(self.is_child, dr.gather(mi.UInt32, si, k, self.is_child), src)
        self.src = src


def add_one_view(grad_accum, view_count, g, visible):
    """One view's statistics added: (grad_accum + g, view_count + 1) where ``visible``
    (``PGADensifier.accumulate``; the recorded training step uses it too)."""
    return grad_accum + dr.select(visible, g, 0.0), view_count + dr.select(visible, 1.0, 0.0)


class PGADensifier:
    """Clone/split/prune with PGA's graph-augmented gradient (see the module docstring).

    State: ``grad_accum`` (sum over views of the detector-plane gradient norm) and
    ``view_count`` (views in which each Gaussian was visible), both mi.Float [N]; None
    until the first ``accumulate`` or ``reset``; ``state_dict()`` / ``load_state_dict()``
    save and restore them (checkpoints).
    """

    def __init__(self, config: Densification | None = None, seed: int = 0,
                 window: DensifyWindow | None = None):
        self.config = config if config is not None else Densification()
        self.window = window if window is not None else DensifyWindow.for_config(self.config)
        _check(self.config, self.window)
        self.seed = int(seed)
        self.grad_accum = None
        self.view_count = None

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """NumPy copy of the accumulators: {"grad_accum": [N], "view_count": [N]} (float32;
        both None before the first ``accumulate`` / ``reset``)."""
        if self.grad_accum is None:
            return {"grad_accum": None, "view_count": None}
        return {"grad_accum": np.asarray(self.grad_accum, np.float32),
                "view_count": np.asarray(self.view_count, np.float32)}

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` output."""
        g, c = state["grad_accum"], state["view_count"]
        if (g is None) != (c is None):
            raise DensifyError("grad_accum and view_count must both be given or both None")
        if g is None:
            self.grad_accum = self.view_count = None
            return
        g, c = np.asarray(g, np.float32).reshape(-1), np.asarray(c, np.float32).reshape(-1)
        if g.shape != c.shape:
            raise DensifyError(f"grad_accum has {g.size} entries, view_count {c.size}")
        # copied, not mapped onto the caller's NumPy memory (mi_grg.training.checkpoint)
        self.grad_accum, self.view_count = mi.Float(np.array(g)), mi.Float(np.array(c))

    # ------------------------------------------------------------------ statistics
    def reset(self, n: int) -> None:
        """Zero the accumulators for ``n`` Gaussians."""
        self.grad_accum = dr.zeros(mi.Float, int(n))
        self.view_count = dr.zeros(mi.Float, int(n))

    @property
    def size(self) -> int | None:
        return None if self.grad_accum is None else dr.width(self.grad_accum)

    def accumulate(self, grad2d_norm, visible=None, n_views: int = 1) -> None:
        """Add one batch of per-(view, Gaussian) gradient norms.

        Args:
            grad2d_norm: mi.Float [n_views * N], view-major (entry v * N + i is
                ||dL/dmu2d|| of Gaussian i in view v), detector-plane units (see tau_pos).
            visible: mi.Bool of the same width (default: all visible). Invisible entries
                neither add to the sum nor count as a view.
            n_views: views in this batch.
        """
        g = mi.Float(grad2d_norm)
        w = dr.width(g)
        if n_views < 1 or w % n_views:
            raise DensifyError(f"grad2d_norm has width {w}, not a multiple of n_views={n_views}")
        n = w // n_views
        if self.grad_accum is None:
            self.reset(n)
        elif n != self.size:
            raise DensifyError(f"grad2d_norm covers {n} Gaussians per view but the "
                               f"accumulators hold {self.size}; call reset(n) after "
                               "changing the set outside step()")
        vis = dr.full(mi.Bool, True, w) if visible is None else mi.Bool(visible)
        if dr.width(vis) != w:
            raise DensifyError(f"visible has width {dr.width(vis)}, grad2d_norm {w}")
        g = dr.detach(g)
        if n_views == 1:
            self.grad_accum, self.view_count = add_one_view(self.grad_accum, self.view_count,
                                                            g, vis)
        else:
            idx = dr.arange(mi.UInt32, w) % n
            acc, cnt = mi.Float(self.grad_accum), mi.Float(self.view_count)
            dr.scatter_add(acc, dr.select(vis, g, 0.0), idx)
            dr.scatter_add(cnt, dr.select(vis, 1.0, 0.0), idx)
            self.grad_accum, self.view_count = acc, cnt
        dr.eval(self.grad_accum, self.view_count)

    def recorded_inputs(self, n: int):
        """The statistics' inputs of a recorded step for N Gaussians (the accumulators,
        zeroed on the first call as ``accumulate`` does), or None where they do not match
        N (``accumulate`` then raises its error)."""
        if self.grad_accum is None:
            self.reset(n)
        if self.size != n:
            return None
        return {"grad_accum": self.grad_accum, "view_count": self.view_count}

    def add(self, stats) -> None:
        """Take one view's statistics added elsewhere (a recorded step's ``add_one_view``
        of ``recorded_inputs``): (grad_accum, view_count)."""
        self.grad_accum, self.view_count = stats

    def averaged_gradient(self) -> "mi.Float":
        """Mean gradient norm over the views that saw each Gaussian (0 if none)."""
        if self.grad_accum is None:
            raise DensifyError("no gradient statistics: call accumulate() first")
        return dr.select(self.view_count > 0,
                         self.grad_accum / dr.maximum(self.view_count, 1.0), 0.0)

    def augmented_gradient(self, graph_term=None) -> "mi.Float":
        """The densification score g_i (module docstring, step 1)."""
        g = self.averaged_gradient()
        if not self.config.use_pga:
            return g
        if graph_term is None:
            raise DensifyError("use_pga=True needs graph_term = mean |rho_i - rho_j| over "
                               "each Gaussian's graph neighbours (mi.Float [N])")
        t = mi.Float(graph_term)
        if dr.width(t) != dr.width(g):
            raise DensifyError(f"graph_term has width {dr.width(t)}, expected {dr.width(g)}")
        return g + self.config.lambda_g * dr.detach(t)

    # ------------------------------------------------------------------ schedule
    def is_densify_iteration(self, iteration: int) -> bool:
        w = self.window
        return iteration in densify_iterations(w.start, w.stop, w.interval, iteration)

    def step(self, iteration: int, raw: dict, optimizer: Adam | None, graph_term=None,
             bbox=None, seed: int | None = None):
        """Densify and prune if ``iteration`` is scheduled; otherwise return ``raw``.

        Args:
            iteration: current iteration (R2-Gaussian counts from 1).
            raw: raw parameters (``Gaussians.to_raw()`` keys), width N.
            optimizer: Adam whose state rows follow the Gaussians (or None).
            graph_term: mi.Float [N], mean |rho_i - rho_j| over graph neighbours (needed
                when use_pga).
            bbox: volume bounding box [[xmin, ymin, zmin], [xmax, ymax, zmax]]
                (``Geometry.bbox()``); required.
            seed: overrides the constructor's seed for the split samples.

        Returns (new raw dict, info dict). New arrays are detached with gradients enabled.
        """
        if not self.is_densify_iteration(iteration):
            return raw, {"densified": False, "n": dr.width(raw["raw_densities"])}
        return self.densify_and_prune(raw, optimizer, graph_term, bbox,
                                      iteration=iteration, seed=seed)

    # ------------------------------------------------------------------ the operation
    def densify_and_prune(self, raw: dict, optimizer: Adam | None, graph_term=None,
                          bbox=None, iteration: int = 0, seed: int | None = None):
        """Unconditional clone/split/prune (``step`` without the schedule check)."""
        n, box = self._checked(raw, optimizer, bbox)
        seed = self.seed if seed is None else int(seed)
        raw = {k: dr.detach(v) for k, v in raw.items()}
        phys = Gaussians.from_raw(raw)
        clone, split, n_cand, capped = self._clone_and_split(phys, graph_term, n, box)
        rows = _Rows(n, clone, split)
        pos, rot, raw_s, raw_d = self._grown(raw, phys, rows, clone, seed, iteration)
        kept = dr.compress(self._keep(box, rows, split, pos, rot, raw_s, raw_d))

        out = {"positions": dr.gather(mi.Point3f, pos, kept),
               "raw_scales": dr.gather(mi.Vector3f, raw_s, kept),
               "raw_rotations": dr.gather(mi.Vector4f, rot, kept),
               "raw_densities": dr.gather(mi.Float, raw_d, kept)}
        for v in out.values():
            dr.enable_grad(v)
        dr.eval(out)
        source = dr.gather(mi.UInt32, rows.src, kept)
        if optimizer is not None:
            optimizer.remap(source, dr.gather(mi.Bool, rows.is_orig, kept))
        n_after = dr.width(kept)
        self.reset(n_after)
        info = {"densified": True, "iteration": int(iteration), "n_before": n,
                "n_candidates": n_cand, "capped": capped, "n_clone": rows.nc,
                "n_split": rows.ns, "n_pruned": rows.m - n_after - rows.ns, "n_after": n_after,
                "source": source}
        return out, info

    def _checked(self, raw: dict, optimizer: Adam | None, bbox):
        """(N, box as a [2, 3] array) after checking the call against the state."""
        n = _check_raw(raw)
        if n == 0:
            raise DensifyError("no Gaussians left to densify (all pruned?)")
        if bbox is None:
            raise DensifyError("bbox is required (Geometry.bbox()): it sets the clone/split "
                               "scale threshold and the pruning box")
        box = _bbox(bbox)
        if self.grad_accum is None:
            self.reset(n)
        if self.size != n:
            raise DensifyError(f"the accumulators hold {self.size} Gaussians, raw has {n}")
        if optimizer is not None and optimizer.width() not in (None, n):
            raise DensifyError(f"the optimiser state has {optimizer.width()} rows, raw has {n}")
        return n, box

    def _clone_and_split(self, phys: Gaussians, graph_term, n: int, box):
        """(clone mask, split mask, candidates, capped): candidates by augmented gradient,
        at most up to the cap; small ones are cloned, large ones split."""
        c = self.config
        score = self.augmented_gradient(graph_term)
        cand = score >= c.densify_grad_threshold
        n_cand = int(dr.count(cand)[0])
        budget = max(self.window.max_count - n, 0)
        capped = n_cand > budget
        if capped:
            cand = self._top_candidates(score, cand, budget)
        s = phys.scales
        smax = dr.maximum(dr.maximum(s.x, s.y), s.z)
        volume_size = float(np.max(box[1] - box[0]))
        thr = c.clone_scale_fraction * volume_size
        return cand & (smax <= thr), cand & (smax > thr), n_cand, capped

    def _grown(self, raw, phys, rows, clone, seed: int, iteration: int):
        """(positions, raw rotations, raw scales, raw densities) of every row: clones and
        the originals they copy halve their density; children shrink and move by a draw
        from their parent's Gaussian."""
        c = self.config
        src, is_orig, is_clone, is_child = rows.src, rows.is_orig, rows.is_clone, rows.is_child
        rho = dr.gather(mi.Float, phys.densities, src)
        halve = is_clone | is_child | (is_orig & dr.gather(mi.Bool, clone, src))
        rho_new = dr.select(halve, 0.5 * rho, rho)
        sc = dr.gather(mi.Vector3f, phys.scales, src)
        sc_new = dr.select(is_child, sc * (1.0 / c.split_scale_factor), sc)
        pos = dr.gather(mi.Point3f, raw["positions"], src)
        rot = dr.gather(mi.Vector4f, raw["raw_rotations"], src)
        if rows.ns:
            q = dr.gather(mi.Vector4f, phys.rotations, src)
            z = standard_normal3(rows.m, seed, iteration)
            offset = mi.Vector3f(rotation_matrix(q) @ (sc * z))   # ~ N(0, R S^2 R^T)
            pos = dr.select(is_child, pos + offset, pos)
        # Changed rows go through the activations; unchanged rows keep raw bit-exactly.
        new_raw = Gaussians(positions=pos, scales=sc_new, rotations=rot,
                            densities=rho_new).to_raw()
        raw_d = dr.select(halve, new_raw["raw_densities"],
                          dr.gather(mi.Float, raw["raw_densities"], src))
        raw_s = dr.select(is_child, new_raw["raw_scales"],
                          dr.gather(mi.Vector3f, raw["raw_scales"], src))
        return pos, rot, raw_s, raw_d

    def _keep(self, box, rows, split, pos, rot, raw_s, raw_d):
        """Rows kept: not a split parent, dense enough, inside the (enlarged) bbox, finite."""
        c = self.config
        lo = box[0] - c.bbox_margin * (box[1] - box[0])
        hi = box[1] + c.bbox_margin * (box[1] - box[0])
        inside = mi.Bool(True)
        for a, comp in enumerate((pos.x, pos.y, pos.z)):
            inside &= (comp >= float(lo[a])) & (comp <= float(hi[a]))
        rho_check = Gaussians.from_raw({"positions": pos, "raw_scales": raw_s,
                                        "raw_rotations": rot,
                                        "raw_densities": raw_d}).densities
        keep = inside & (rho_check >= c.min_density) & dr.isfinite(rho_check)
        keep &= ~(rows.is_orig & dr.gather(mi.Bool, split, rows.src))
        return keep

    @staticmethod
    def _top_candidates(score, cand, budget: int):
        """The ``budget`` candidates with the largest score (ties: lower index first).
        Host-side argsort: runs once per densification, on N floats."""
        if budget <= 0:
            return dr.full(mi.Bool, False, dr.width(cand))
        s = np.asarray(score, dtype=np.float64)
        s = np.where(np.asarray(cand, dtype=bool), s, -np.inf)
        order = np.argsort(-s, kind="stable")[:budget]
        mask = np.zeros(s.size, dtype=bool)
        mask[order] = True
        return mi.Bool(mask)
