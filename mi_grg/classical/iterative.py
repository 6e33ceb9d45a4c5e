"""Iterative baselines in Dr.Jit: SART / OS-SART and ASD-POCS (SART + total variation).

SART (Andersen & Kak 1984), OS-SART with subsets of ``blocksize`` views; for every subset s

    x <- x + lambda * V_s * A_s^T( W * (b_s - A_s x) ),   then x <- max(x, 0)

with A the Joseph projector (``voxel_projector``), W = 1 / (row sums of A) per ray (= 1 /
chord length through the volume box) and V_s = 1 / (column sums of A_s) per voxel, both
computed by projecting ones; rays shorter than a quarter voxel and voxels no ray of the
subset sees get weight 0 (as in TIGRE). lambda is multiplied by ``relaxation_decay`` after
every sweep. Defaults follow TIGRE: lambda = 1, decay 0.99, non-negativity on, zero
initialisation, blocksize 1 for SART and 20 for OS-SART.

ASD-POCS (Sidky & Pan 2008, with TIGRE's defaults: alpha = 0.002, alpha_red = 0.95,
ng = 20 TV steps, r_max = 0.95, epsilon = 0.2 x the data residual of FDK): every iteration
is one SART sweep (data consistency + positivity) followed by ``ng`` steps of normalised
steepest descent on the 3-D isotropic total variation, with the adaptive step size rules
of the paper.

Iteration counts: on sparse (25) noisy views both methods *semi-converge*: the PSNR against
the ground truth peaks after a few sweeps and then falls as the data's noise and the
model mismatch of exact (not voxelised) line integrals are fitted. ``n_iter`` is therefore
the main regulariser; the default of 10 is a compromise measured on Shepp-Logan at
48^3-128^3 (see docs/bench/baselines.md).

Volumes are [x, y, z] densities (1 / length); projections [view, v, u] line integrals.
"""
from __future__ import annotations

import sys

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core.geometry import Geometry
from mi_grg.core.joseph import (JosephProjector, check_angles, check_projections,
                                forward_project)
from mi_grg.protocol.heldout import check_stop, run_heldout
from mi_grg.protocol.search import LogGrid

ORDERS = ("ordered", "random", "angular")
#: Largest memory (bytes) spent on caching the per-subset column sums V_s.
V_CACHE_BYTES = 1 << 30


# ---------------------------------------------------------------- subsets
def order_subsets(angles, blocksize: int, order: str = "angular", seed: int = 0) -> list:
    """Split view indices into subsets of ``blocksize`` consecutive views and order them.

    ``ordered``: as given; ``random``: a seeded permutation; ``angular``: greedily pick the
    next subset whose mean angle is farthest (on the circle) from those already used
    (TIGRE's "angularDistance"), which spreads consecutive updates over the circle.
    ``order`` may also be an explicit permutation of the subset indices.
    Returns a list of int arrays."""
    blocksize = int(blocksize)
    if blocksize < 1:
        raise ValueError(f"blocksize must be >= 1 view, got {blocksize}")
    a = np.asarray(angles, np.float64).reshape(-1)
    idx = np.arange(a.size)
    blocks = [idx[i:i + blocksize] for i in range(0, a.size, blocksize)]
    if not isinstance(order, str):
        perm = np.asarray(order).reshape(-1)
        if sorted(perm.tolist()) != list(range(len(blocks))):
            raise ValueError(f"an explicit order must be a permutation of the {len(blocks)} "
                             f"subset indices, got {order!r}")
        return [blocks[int(i)] for i in perm]
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS} or a permutation, got {order!r}")
    if order == "ordered" or len(blocks) == 1:
        return blocks
    if order == "random":
        perm = np.random.default_rng(seed).permutation(len(blocks))
        return [blocks[i] for i in perm]
    mean = np.array([np.angle(np.mean(np.exp(1j * a[b]))) for b in blocks])
    used = [0]
    left = list(range(1, len(blocks)))
    while left:
        d = np.abs(np.angle(np.exp(1j * (mean[left][:, None] - mean[used][None, :]))))
        # Equally spaced angles tie exactly in theory but not in float rounding: round, then
        # break ties by the distance from the last subset, so that consecutive updates stay
        # far apart whatever the rounding of this machine.
        far_from_all = np.round(d.min(axis=1), 9)
        far_from_last = np.round(d[:, -1], 9)
        pick = left[int(np.lexsort((-far_from_last, -far_from_all))[0])]
        used.append(pick)
        left.remove(pick)
    return [blocks[i] for i in used]


# ---------------------------------------------------------------- total variation
def _tv_neighbours(x, shape):
    Float, Int, UInt = mi.Float, mi.Int32, mi.UInt32
    nx, ny, nz = shape
    strides = (ny * nz, nz, 1)
    sizes = (nx, ny, nz)
    i = dr.arange(Int, nx * ny * nz)
    coord = (i // (ny * nz), (i // nz) % ny, i % nz)

    def at(offsets):
        """x at i + offsets (0 outside the volume) and whether that point is inside."""
        j = i
        ok = dr.full(mi.Bool, True, nx * ny * nz)
        for a, o in enumerate(offsets):
            if o:
                c = coord[a] + o
                ok &= (c >= 0) & (c < sizes[a])
                j = j + o * strides[a]
        return dr.gather(Float, x, UInt(j), ok), ok
    return at


def tv_gradient(x, shape, eps: float = 1e-8):
    """Gradient of the isotropic 3-D total variation
    TV(x) = sum_i sqrt(eps + sum_a (D_a x)_i^2), with forward differences D_a (zero across
    the far boundary). ``x`` flat mi.Float [x, y, z]; returns flat mi.Float."""
    at = _tv_neighbours(x, shape)
    e = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    x0, _ = at((0, 0, 0))

    def diffs(base):
        """Forward differences (3) at voxel i + base and their norm; validity of i+base."""
        xb, ok = at(base)
        d = []
        for a in range(3):
            xn, okn = at(tuple(b + o for b, o in zip(base, e[a])))
            d.append(dr.select(okn & ok, xn - xb, 0.0))
        return d, dr.sqrt(eps + d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), ok

    d0, n0, _ = diffs((0, 0, 0))
    g = -(d0[0] + d0[1] + d0[2]) / n0
    for a in range(3):
        back = tuple(-o for o in e[a])
        da, na, ok = diffs(back)
        g += dr.select(ok, da[a] / na, 0.0)
    return g


def tv_value(x: np.ndarray, eps: float = 1e-8) -> float:
    """Isotropic TV of a numpy volume [x, y, z] (float64), matching ``tv_gradient``."""
    x = np.asarray(x, np.float64)
    d = [np.diff(x, axis=a, append=np.take(x, [-1], axis=a)) for a in range(3)]
    return float(np.sum(np.sqrt(eps + d[0] ** 2 + d[1] ** 2 + d[2] ** 2)))


def _norm(x) -> float:
    return float(dr.sqrt(dr.sum(dr.square(x), mode="evaluated"))[0])


# ---------------------------------------------------------------- SART engine
class _SART:
    """Weights, subsets and one sweep of (OS-)SART for a fixed data set."""

    def __init__(self, proj: np.ndarray, geometry: Geometry, angles: np.ndarray,
                 blocksize: int, order: str, seed: int):
        self.geo = geometry
        self.angles = angles
        self.A = JosephProjector(geometry)
        self.n_pix = self.A.n_pix
        self.subsets = order_subsets(angles, blocksize, order, seed)
        flat = proj.reshape(len(angles), -1)
        self.b = [mi.Float(np.ascontiguousarray(flat[s]).reshape(-1)) for s in self.subsets]
        self.b_all = mi.Float(flat.reshape(-1))
        self.b_norm = float(np.linalg.norm(flat.astype(np.float64)))
        # row sums of all views in one projection; subsets are runs of consecutive views
        rows_all = self.A.forward(dr.full(mi.Float, 1.0, self.A.n_vox), angles)
        row_min = 0.25 * min(geometry.dVoxel)
        self.W = []
        for s in self.subsets:
            rows = dr.gather(mi.Float, rows_all, dr.arange(mi.UInt32, len(s) * self.n_pix)
                             + dr.opaque(mi.UInt32, int(s[0]) * self.n_pix))
            self.W.append(dr.select(rows > row_min, 1.0 / dr.maximum(rows, row_min), 0.0))
        dr.eval(self.W)
        self.cache_V = len(self.subsets) * self.A.n_vox * 4 <= V_CACHE_BYTES
        self._V = [self._column_weights(s) for s in self.subsets] if self.cache_V else None

    def _column_weights(self, s):
        ones = dr.full(mi.Float, 1.0, len(s) * self.n_pix)
        cols = self.A.adjoint(ones, self.angles[s])
        col_min = 1e-4 * min(self.geo.dVoxel)
        v = dr.select(cols > col_min, 1.0 / dr.maximum(cols, col_min), 0.0)
        dr.eval(v)
        return v

    def sweep(self, x, lam: float, nonneg: bool):
        """One pass over all subsets; returns (x, relative residual norm ||b - A x|| / ||b||
        accumulated over the subsets just before their updates)."""
        # Scalars that change between calls are opaque, so the kernels compile once.
        lam = dr.opaque(mi.Float, lam)
        res2 = dr.zeros(mi.Float, 1)
        for k, s in enumerate(self.subsets):
            r = self.b[k] - self.A.forward(x, self.angles[s])
            dr.eval(r)
            res2 += dr.sum(dr.square(r), mode="evaluated")
            upd = self.A.adjoint(r * self.W[k], self.angles[s])
            V = self._V[k] if self.cache_V else self._column_weights(s)
            x = dr.fma(lam * V, upd, x)
            if nonneg:
                x = dr.maximum(x, 0.0)
            dr.eval(x, res2)
        return x, float(np.sqrt(res2.numpy()[0])) / max(self.b_norm, 1e-30)

    def residual(self, x) -> float:
        """||A x - b||_2 over all views (absolute, density x length)."""
        r = self.A.forward(x, self.angles) - self.b_all
        return _norm(r)


def _initial(init, proj, geometry, angles, n_vox):
    if init is None or (isinstance(init, str) and init == "zeros"):
        return dr.zeros(mi.Float, n_vox)
    if isinstance(init, str):
        if init != "fdk":
            raise ValueError(f"init must be 'zeros', 'fdk' or a volume [x, y, z], got {init!r}")
        from mi_grg.core.fdk import fdk_dr
        return dr.maximum(fdk_dr(proj, geometry, angles).array, 0.0)
    from mi_grg.core.joseph import check_volume
    return mi.Float(check_volume(init, geometry, "init").reshape(-1))


def _check_inputs(proj, geometry: Geometry, angles, n_iter) -> tuple:
    """(angles, projections) checked against the scan, and n_iter >= 1: the inputs every
    iterative solver (SART, ASD-POCS, PDHG) validates first."""
    a = check_angles(angles, geometry)
    p = check_projections(proj, geometry, a)
    if int(n_iter) < 1:
        raise ValueError(f"n_iter must be >= 1, got {n_iter}")
    return a, p


def _progress(total, desc, progress):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, file=sys.stderr, disable=not progress, leave=True)


def _to_numpy(x, geometry):
    return np.array(x.numpy(), dtype=np.float32, copy=True).reshape(geometry.nVoxel)


# ---------------------------------------------------------------- public API
def sart(proj, geometry: Geometry, angles=None, *, n_iter: int = 10, blocksize: int = 1,
         relaxation: float = 1.0, relaxation_decay: float = 0.99, nonneg: bool = True,
         init=None, order: str = "angular", tol: float = 0.0, seed: int = 0,
         progress: bool = True, callback=None) -> np.ndarray:
    """SART (blocksize 1) / OS-SART (blocksize > 1) reconstruction.

    Args:
        proj: line integrals [view, v, u] = (len(angles), *nDetector).
        geometry: the scan; ``angles`` (radians) overrides ``geometry.angles``.
        n_iter: sweeps over all views (>= 1).
        blocksize: views per subset (1 = SART, TIGRE's OS-SART default is 20).
        relaxation: lambda, the step of each subset update (0 < lambda < 2).
        relaxation_decay: lambda is multiplied by this after every sweep.
        nonneg: clip negative densities after every update.
        init: None / "zeros", "fdk", or a volume [x, y, z].
        order: subset order, one of "ordered", "random", "angular", or an explicit
            permutation of the subset indices.
        tol: stop when the relative change of the sweep residual falls below ``tol``
            (0 disables).
        progress: tqdm bar on stderr (iteration, elapsed time and the relative residual
            ||b - A x|| / ||b|| accumulated over the subsets just before their updates).
        callback: optional ``f(iteration, volume numpy [x, y, z])`` after every sweep; a
            true return value ends the run (held-out-view stopping, mi_grg.protocol.heldout).
    Returns:
        float32 [x, y, z] densities.
    """
    a, p = _check_inputs(proj, geometry, angles, n_iter)
    if not 0 < relaxation < 2:
        raise ValueError(f"relaxation must be in (0, 2), got {relaxation}")
    eng = _SART(p, geometry, a, blocksize, order, seed)
    x = _initial(init, p, geometry, a, eng.A.n_vox)
    lam, prev = float(relaxation), None
    with _progress(int(n_iter), "SART" if blocksize == 1 else "OS-SART", progress) as bar:
        for it in range(int(n_iter)):
            x, res = eng.sweep(x, lam, nonneg)
            lam *= relaxation_decay
            bar.set_postfix(residual=f"{res:.3e}")
            bar.update(1)
            if callback is not None and callback(it, _to_numpy(x, geometry)):
                break
            if tol > 0 and prev is not None and abs(prev - res) <= tol * prev:
                break
            prev = res
    return _to_numpy(x, geometry)


def asd_pocs(proj, geometry: Geometry, angles=None, *, n_iter: int = 10, tv_iters: int = 20,
             alpha: float = 0.002, alpha_red: float = 0.95, r_max: float = 0.95,
             epsilon=None, relaxation: float = 1.0, relaxation_decay: float = 0.99,
             blocksize: int = 1, nonneg: bool = True, init=None, order: str = "angular",
             tv_eps: float = 1e-8, seed: int = 0, progress: bool = True,
             callback=None) -> np.ndarray:
    """ASD-POCS (Sidky & Pan 2008) with TIGRE's defaults.

    Args:
        proj, geometry, angles: as for ``sart``.
        n_iter: outer iterations (each one SART sweep + ``tv_iters`` TV steps).
        tv_iters: ng, steepest-descent TV steps per iteration.
        alpha: TV step as a fraction of the size of the first SART update.
        alpha_red: factor on the TV step when it dominates the data step.
        r_max: maximum allowed ratio (TV change) / (SART change) before reducing the step.
        epsilon: data-residual tolerance ||A x - b||_2 (density x length); None = 0.2 x
            the residual of the FDK reconstruction.
        relaxation, relaxation_decay: SART lambda and its decay per iteration (beta and
            beta_red in the paper); the loop stops once lambda < 0.005.
        blocksize, nonneg, init, order, seed: SART options (blocksize 1 as in TIGRE).
        tv_eps: smoothing of the TV norm, sqrt(eps + |grad x|^2).
        progress: tqdm bar on stderr (iteration, data residual, elapsed time).
        callback: optional ``f(iteration, volume numpy [x, y, z])``; a true return value
            ends the run.
    Returns:
        float32 [x, y, z] densities.
    """
    a, p = _check_inputs(proj, geometry, angles, n_iter)
    if int(tv_iters) < 0:
        raise ValueError(f"tv_iters must be >= 0, got {tv_iters}")
    eng = _SART(p, geometry, a, blocksize, order, seed)
    shape = tuple(geometry.nVoxel)
    if epsilon is None:
        from mi_grg.core.fdk import fdk_dr
        epsilon = 0.2 * eng.residual(fdk_dr(p, geometry, a).array)
    x = _initial(init, p, geometry, a, eng.A.n_vox)
    beta = float(relaxation)
    dtvg = None
    with _progress(int(n_iter), "ASD-POCS", progress) as bar:
        for it in range(int(n_iter)):
            x_prev = x
            x, _ = eng.sweep(x, beta, nonneg)
            dd = eng.residual(x)
            dp_vec = x - x_prev
            dp = _norm(dp_vec)
            if dtvg is None:
                dtvg = alpha * dp
            x_prev = x
            for _ in range(int(tv_iters)):
                g = tv_gradient(x, shape, tv_eps)
                gn = _norm(g)
                if gn <= 0:
                    break
                x = dr.fma(dr.opaque(mi.Float, -dtvg / gn), g, x)
                dr.eval(x)
            dg_vec = x - x_prev
            dg = _norm(dg_vec)
            if dg > r_max * dp and dd > epsilon:
                dtvg *= alpha_red
            beta *= relaxation_decay
            c = float(dr.sum(dg_vec * dp_vec, mode="evaluated")[0]) / max(dg * dp, 1e-30)
            bar.set_postfix(residual=f"{dd:.3e}", eps=f"{epsilon:.2e}")
            bar.update(1)
            if callback is not None and callback(it, _to_numpy(x, geometry)):
                break
            if (c < -0.99 and dd <= epsilon) or beta < 0.005:
                break
    return _to_numpy(x, geometry)


# ---------------------------------------------------------------- reconstruction contract
#: Sweeps of ``stop="none"`` when n_iter is not given (TIGRE's examples; the paper's tables).
FIXED_SWEEPS = 10
#: Cap on sweeps per candidate under ``stop="heldout"``: twice TIGRE's 10. On noisy
#: sparse views the held-out-view PSNR often keeps rising to the cap long after the 3-D
#: PSNR peaked; the sweep count then comes from the discrepancy principle
#: (mi_grg.protocol.heldout, step 3), and the cap bounds the noise-level estimate's runs.
HELDOUT_SWEEP_CAP = 20
#: ASD-POCS's TV weights tried first under ``stop="heldout"``: TIGRE's default 0.002 and
#: half-decades above it (the TV step as a fraction of the first SART update); the search
#: widens past whichever end wins (``weight_grid``).
ALPHA_GRID = (0.002, 0.006, 0.02, 0.06)
#: ASD-POCS's weight rules (``alpha_rule``; mi_grg.protocol.search.RULES), the default
#: first: Morozov's weight rule and the discrepancy sweep rule ASD-POCS stops by exclude
#: each other.
ALPHA_RULES = ("one_se", "best")
#: Values a weight search may add past each end of its grid (half-decades: two decades).
GRID_EXTEND = 4


def _as_grid(value, name: str, default) -> list:
    """A number, a list of numbers, or None (``default``) as a list of candidates >= 0."""
    vals = list(default) if value is None else (
        list(value) if isinstance(value, (list, tuple)) else [value])
    if not vals or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           and np.isfinite(v) and v >= 0 for v in vals):
        raise ValueError(f"{name} must be a number >= 0 or a list of them, got {value!r}")
    return [float(v) for v in vals]


def weight_grid(value, name: str, default, rule: str = "one_se"):
    """What ``run_heldout`` searches for one weight: a number fixes it (a list of one
    setting); None (``default``) or a list is a ``LogGrid`` that widens past a winning end
    until its choice is interior (``mi_grg.protocol.search``), the choice made by ``rule``
    (the one-standard-error rule unless told: ``mi_grg.protocol.heldout``). A list holding 0 (no
    regulariser), which no log grid can widen, is tried as given."""
    vals = _as_grid(value, name, default)
    if value is not None and not isinstance(value, (list, tuple)):
        return [{name: vals[0]}]
    if 0.0 in vals:
        if len(set(vals)) != len(vals) or len(vals) < 2:
            raise ValueError(f"{name}: a grid needs at least two distinct values, got "
                             f"{value!r} (give one number to fix the weight)")
        return [{name: v} for v in vals]
    return LogGrid(name, vals, max_extend=GRID_EXTEND, rule=rule)


def _one(value, name: str) -> float:
    """A single number >= 0 (a stop="none" run has no grid to choose from)."""
    if isinstance(value, (list, tuple)):
        raise ValueError(f"{name}: a list of candidates needs stop='heldout' to choose "
                         f"among them; give one number with stop='none', got {value!r}")
    return _as_grid(value, name, ())[0]


def reconstruct_sart(case, *, stop: str = "heldout", n_iter=None, blocksize: int = 1,
                     relaxation: float = 1.0, relaxation_decay: float = 0.99,
                     nonneg: bool = True, init=None, order: str = "angular", tol: float = 0.0,
                     seed: int = 0, holdout_every=None, oracle=None, progress: bool = True):
    """The ``--method sart`` entry point: (OS-)SART of ``case.train`` in ``case.geometry``.

    Options (see ``sart``): stop ("heldout": the sweep count is chosen by the discrepancy
    principle with the noise level measured on held-out views, then run on all views,
    mi_grg.protocol.heldout; "none": exactly
    n_iter sweeps, the paper's tables), n_iter (under "heldout" a cap, default
    HELDOUT_SWEEP_CAP; under "none" default FIXED_SWEEPS), blocksize (1 = SART; e.g. 20 =
    OS-SART, which moves less per sweep: raise the cap n_iter with it), relaxation (lambda, 1.0), relaxation_decay (0.99 per sweep), nonneg (True),
    init (None/"zeros", "fdk" or a volume), order ("angular"), tol (0 = no residual test),
    seed, holdout_every (None = gr's), oracle (None = score sweeps when a ground truth
    exists), progress (tqdm on stderr). Returns float32 [x, y, z] (and, under "heldout",
    what was decided); unknown options raise.
    """
    opts = dict(blocksize=blocksize, relaxation=relaxation, relaxation_decay=relaxation_decay,
                nonneg=nonneg, init=init, order=order, tol=tol, seed=seed)
    if _fixed(stop, holdout_every, oracle, "sart"):
        return sart(case.train, case.geometry, n_iter=FIXED_SWEEPS if n_iter is None
                    else n_iter, progress=progress, **opts)
    return run_heldout(case, lambda p, g, **kw: sart(p, g, **opts, **kw), [{}],
                       project=forward_project,
                       max_sweeps=HELDOUT_SWEEP_CAP if n_iter is None else n_iter,
                       name="sart", holdout_every=holdout_every, oracle=oracle,
                       discrepancy=True, progress=progress)


def _fixed(stop, holdout_every, oracle, name) -> bool:
    """True for ``stop="none"``; options that only the held-out protocol reads raise there."""
    if check_stop(stop) == "heldout":
        return False
    given = [k for k, v in (("holdout_every", holdout_every), ("oracle", oracle))
             if v is not None]
    if given:
        raise ValueError(f"{name}: option(s) {given} apply to stop='heldout' only")
    return True


def reconstruct_asd_pocs(case, *, stop: str = "heldout", n_iter=None, tv_iters: int = 20,
                         alpha=None, alpha_red: float = 0.95, r_max: float = 0.95,
                         epsilon=None, relaxation: float = 1.0, relaxation_decay: float = 0.99,
                         blocksize: int = 1, nonneg: bool = True, init=None,
                         order: str = "angular", tv_eps: float = 1e-8, seed: int = 0,
                         alpha_rule=None, holdout_every=None, oracle=None,
                         progress: bool = True):
    """The ``--method asd-pocs`` entry point (see ``asd_pocs`` for every option).

    Options: stop ("heldout": the sweep count (discrepancy principle, the noise level
    measured on held-out views) AND the TV weight alpha (held-out PSNR) are chosen without
    the ground truth, then run on all views; "none": n_iter sweeps at one alpha), n_iter
    (cap under "heldout", HELDOUT_SWEEP_CAP; FIXED_SWEEPS under "none"), alpha (None =
    ALPHA_GRID under "heldout" and TIGRE's 0.002 under "none"; a number or, under
    "heldout", a list of candidates; the search widens the list or ALPHA_GRID past a winning
    end, metrics.json's method_info.search says where it ended), alpha_rule (how "heldout"
    chooses alpha from a grid: None / "one_se", the one-standard-error rule, or "best", the
    best held-out PSNR; Morozov's weight rule excludes the discrepancy sweep rule ASD-POCS
    uses), tv_iters (ng, 20), alpha_red (0.95), r_max (0.95),
    epsilon (None = 0.2 x FDK residual), relaxation (1.0), relaxation_decay (0.99),
    blocksize (1), nonneg (True), init (None), order ("angular"), tv_eps (1e-8), seed,
    holdout_every, oracle (as for sart), progress. Returns float32 [x, y, z] (and, under
    "heldout", what was decided); unknown options raise.
    """
    opts = dict(tv_iters=tv_iters, alpha_red=alpha_red, r_max=r_max, epsilon=epsilon,
                relaxation=relaxation, relaxation_decay=relaxation_decay,
                blocksize=blocksize, nonneg=nonneg, init=init, order=order, tv_eps=tv_eps,
                seed=seed)
    if _fixed(stop, holdout_every, oracle, "asd-pocs"):
        if alpha_rule is not None:
            raise ValueError("asd-pocs: alpha_rule chooses alpha on held-out views; it "
                             "needs stop='heldout'")
        a = _one(0.002 if alpha is None else alpha, "alpha")
        return asd_pocs(case.train, case.geometry, n_iter=FIXED_SWEEPS if n_iter is None
                        else n_iter, alpha=a, progress=progress, **opts)
    if alpha_rule is not None and alpha_rule not in ALPHA_RULES:
        raise ValueError(f"asd-pocs: alpha_rule must be one of {', '.join(ALPHA_RULES)}, "
                         f"got {alpha_rule!r}")
    grid = weight_grid(alpha, "alpha", ALPHA_GRID, alpha_rule or ALPHA_RULES[0])
    if alpha_rule is not None and not isinstance(grid, LogGrid):
        raise ValueError(f"asd-pocs: alpha_rule={alpha_rule!r} chooses among a grid of "
                         f"alpha; alpha={alpha!r} leaves nothing to choose")
    return run_heldout(case, lambda p, g, **kw: asd_pocs(p, g, **opts, **kw), grid,
                       project=forward_project,
                       max_sweeps=HELDOUT_SWEEP_CAP if n_iter is None else n_iter,
                       name="asd-pocs", holdout_every=holdout_every, oracle=oracle,
                       discrepancy=True, progress=progress)
