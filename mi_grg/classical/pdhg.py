"""Chambolle-Pock primal-dual (PDHG) for total-variation CT, on the Joseph projector.

Problem (volumes [x, y, z] densities, projections [view, v, u] line integrals):

    min_x  1/2 ||A x - b||^2 + lambda TV(x)   subject to 0 <= x (<= upper)

with A the Joseph projector (``mi_grg.core.joseph``) and TV(x) = sum_i |(D x)_i|_2 the
isotropic total variation, D the forward differences of ``gradient`` (zero across the far
boundary), D^T = -``divergence``. Chambolle & Pock (2011), algorithm 1 with theta = 1, on
K = [A; mu D], F(y1, y2) = 1/2 ||y1 - b||^2 + (lambda / mu) sum |y2_i|_2, G = the box:

    y1 <- (y1 + sigma (A xb - b)) / (1 + sigma)
    y2 <- project (y2 + sigma mu D xb) onto {|y2_i|_2 <= lambda / mu}
    x' <- clip(x - tau (A^T y1 - mu div y2), 0, upper);   xb <- 2 x' - x;   x <- x'

mu = ||A|| / ||D|| balances the two blocks (so ||K||^2 <= 2 ||A||^2); ||A|| comes from a
power iteration on A^T A, ||D|| <= sqrt(12) in 3-D (closed-form bound); the steps satisfy
sigma tau ||K||^2 = 0.99 < 1, which the convergence proof needs, with sigma / tau =
``gamma``^2 (``gamma`` = sigma ||K||, the balance between primal and dual steps).

``lam`` (the option) is dimensionless: lambda = lam x max(A^T b), so the same value poses
the same problem in mm or in R2-Gaussian's normalised units and for any density scale
(both terms of the objective scale alike). The step balance ``gamma`` is not unit-free.

``PDHG.gap`` is the primal-dual gap of this saddle-point problem for a finite ``upper``
(G* of a box is finite; with no upper bound the dual is -inf off a cone).
"""
from __future__ import annotations

import math
import time

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core.geometry import Geometry
from mi_grg.core.joseph import JosephProjector
from mi_grg.classical.iterative import (_check_inputs, _fixed, _initial, _one, _progress,
                                        _to_numpy, weight_grid)
from mi_grg.core.joseph import forward_project
from mi_grg.evaluation.metrics import psnr_3d
from mi_grg.protocol.heldout import oracle_info, run_heldout
from mi_grg.protocol.search import RULES, LogGrid

#: ||D||^2 <= 4 per axis for forward differences, 12 in 3-D.
GRAD_NORM = math.sqrt(12.0)
#: sigma tau ||K||^2 (must be < 1).
STEP_SAFETY = 0.99
#: sigma ||K||: sigma / tau = gamma^2. Measured on shepp 64^3 in load_case's normalised units
#: (docs/bench/fair_baselines.md); the balance depends on the length unit.
DEFAULT_GAMMA = 0.3
#: Projected-gradient steps that fit a warm start's TV dual (``PDHG._warm_duals``).
WARM_DUAL_ITERATIONS = 200
#: Iterations of ``stop="none"`` when n_iter is not given.
FIXED_ITERATIONS = 100
#: Cap on iterations per candidate under ``stop="heldout"`` on a 64^3 grid
#: (``heldout_cap`` scales it with the grid; docs/bench/pdhg_cap_n.md).
HELDOUT_ITERATION_CAP = 60
#: The grid size (longest axis, voxels) that HELDOUT_ITERATION_CAP was chosen at.
HELDOUT_CAP_SIZE = 64
#: Whether the held-out cap widens by default (``widen``; docs/bench/pdhg_rules.md).
WIDEN_CAP = False
#: Held-out evaluations every this many iterations: an iteration moves far less than a
#: SART sweep (one simultaneous update instead of one per view).
EVAL_EVERY = 5
#: lam (TV weight / max(A^T b)) tried first under ``stop="heldout"``; the search widens
#: past whichever end wins (``mi_grg.classical.iterative.weight_grid``).
LAM_GRID = (0.001, 0.003, 0.01)
#: How ``stop="heldout"`` chooses lam when ``lam_rule`` is not given (docs/bench/pdhg_rules.md).
DEFAULT_LAM_RULE = "one_se"
#: Default lam under ``stop="none"``.
FIXED_LAM = 0.003



# ---------------------------------------------------------------- finite differences
def _axes(shape):
    nx, ny, nz = (int(s) for s in shape)
    i = dr.arange(mi.Int32, nx * ny * nz)
    coord = (i // (ny * nz), (i // nz) % ny, i % nz)
    return i, coord, (ny * nz, nz, 1), (nx, ny, nz)


def gradient(x, shape) -> list:
    """Forward differences D x of a flat volume [x, y, z]: three flat mi.Float, zero at the
    last index of each axis (Neumann boundary)."""
    i, coord, strides, sizes = _axes(shape)
    out = []
    for a in range(3):
        inside = coord[a] < sizes[a] - 1
        nxt = dr.gather(mi.Float, x, mi.UInt32(i + strides[a]), inside)
        out.append(dr.select(inside, nxt - x, 0.0))
    return out


def divergence(p, shape):
    """div p = -D^T p for three flat mi.Float fields [x, y, z] (``gradient``'s adjoint)."""
    i, coord, strides, sizes = _axes(shape)
    out = dr.zeros(mi.Float, dr.width(i))
    for a in range(3):
        here = dr.select(coord[a] < sizes[a] - 1, p[a], 0.0)
        has_prev = coord[a] > 0
        prev = dr.gather(mi.Float, p[a], mi.UInt32(dr.select(has_prev, i - strides[a], 0)),
                         has_prev)
        out += here - prev
    return out


def tv_iso(x, shape) -> float:
    """sum_i |(D x)_i|_2 of a flat volume (float, accumulated in float32)."""
    g = gradient(x, shape)
    return float(dr.sum(dr.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]),
                        mode="evaluated")[0])


def _dot(a, b) -> float:
    return float(dr.sum(a * b, mode="evaluated")[0])


# ---------------------------------------------------------------- operator norm
def operator_norm(A: JosephProjector, angles, n_iter: int = 20, seed: int = 0) -> float:
    """||A||_2 by power iteration on A^T A (a lower estimate that rises with n_iter;
    callers add a margin)."""
    rng = np.random.default_rng(seed)
    x = mi.Float(rng.random(A.n_vox).astype(np.float32))
    x /= dr.sqrt(dr.sum(x * x, mode="evaluated"))
    s = 0.0
    for _ in range(int(n_iter)):
        y = A.adjoint(A.forward(x, angles), angles)
        n = math.sqrt(max(_dot(y, y), 0.0))
        if n == 0:
            return 0.0
        s = n
        x = y / n
        dr.eval(x)
    return math.sqrt(s)


# ---------------------------------------------------------------- solver
class PDHG:
    """The iteration of the module docstring for one data set; ``step()`` runs one
    iteration, ``x`` is the current primal volume (flat mi.Float)."""

    def __init__(self, proj: np.ndarray, geometry: Geometry, angles: np.ndarray, *,
                 lam: float, upper=None, gamma: float = DEFAULT_GAMMA, norm_A=None,
                 power_iters: int = 8, nonneg: bool = True, init=None):
        if not (math.isfinite(lam) and lam >= 0):
            raise ValueError(f"lam must be a finite number >= 0, got {lam}")
        if not (math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be a finite number > 0, got {gamma}")
        if upper is not None and not (math.isfinite(upper) and upper > 0):
            raise ValueError(f"upper must be None or a finite density > 0, got {upper}")
        self.geo, self.angles, self.shape = geometry, angles, tuple(geometry.nVoxel)
        self.A = JosephProjector(geometry)
        self.b = mi.Float(np.ascontiguousarray(proj, np.float32).reshape(-1))
        self.norm_A = float(norm_A) if norm_A else operator_norm(self.A, angles, power_iters)
        if self.norm_A <= 0:
            raise ValueError("the projector is zero on this geometry (no ray meets the volume)")
        # 2 % margin: the power iteration approaches ||A|| from below.
        nA = 1.02 * self.norm_A
        self.mu = nA / GRAD_NORM
        L = math.sqrt(2.0) * nA                        # ||K|| <= sqrt(||A||^2 + mu^2 12)
        self.sigma = gamma / L * math.sqrt(STEP_SAFETY)
        self.tau = 1.0 / (gamma * L) * math.sqrt(STEP_SAFETY)
        atb = self.A.adjoint(self.b, angles)
        self.lam_abs = float(lam) * float(dr.max(atb, mode="evaluated")[0])
        self.upper, self.nonneg = upper, nonneg
        n = self.A.n_vox
        # a warm start (a volume [x, y, z]) is moved into the box first: x must be feasible
        self.x = self._clip(_initial(init, proj, geometry, angles, n))
        self.xb = mi.Float(self.x)
        self.y1 = dr.zeros(mi.Float, dr.width(self.b))
        self.y2 = [dr.zeros(mi.Float, n) for _ in range(3)]
        if init is not None and not (isinstance(init, str) and init == "zeros"):
            self._warm_duals()

    def _warm_duals(self):
        """Duals at their fixed point for the current x: y1 = A x - b (the data term's),
        y2 = bound D x / |D x| (the TV term's, 0 where flat). From zero duals a warm start
        first moves x by a TV flow with no data term to balance it, which a held-out
        decision sees as a transient loss of the start's quality."""
        self.y1 = self.A.forward(self.x, self.angles) - self.b
        g = gradient(self.x, self.shape)
        norm = dr.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        bound = self.lam_abs / self.mu
        scale = dr.select(norm > 0, bound / dr.maximum(norm, 1e-30), 0.0)
        y2 = [g[a] * scale for a in range(3)]
        # Where the volume is nearly flat that guess is arbitrary; move y2 towards the
        # primal optimality condition mu div y2 = A^T y1 (projected gradient, |y2| <= bound)
        aty = self.A.adjoint(self.y1, self.angles)
        t = 1.0 / (self.mu * self.mu * GRAD_NORM * GRAD_NORM)
        for _ in range(WARM_DUAL_ITERATIONS):
            d = gradient(self.mu * divergence(y2, self.shape) - aty, self.shape)
            z = [y2[a] + t * self.mu * d[a] for a in range(3)]
            n = dr.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
            shrink = dr.select(n > bound, bound / dr.maximum(n, 1e-30), 1.0)
            y2 = [z[a] * shrink for a in range(3)]
            dr.eval(y2)
        self.y2 = y2
        dr.eval(self.y1, self.y2)

    def _clip(self, x):
        if self.nonneg:
            x = dr.maximum(x, 0.0)
        if self.upper is not None:
            x = dr.minimum(x, self.upper)
        return x

    def step(self):
        # opaque scalars: the kernels compile once whatever the step sizes
        sig = dr.opaque(mi.Float, self.sigma)
        tau = dr.opaque(mi.Float, self.tau)
        mu = dr.opaque(mi.Float, self.mu)
        bound = dr.opaque(mi.Float, self.lam_abs / self.mu)
        r = self.A.forward(self.xb, self.angles) - self.b
        self.y1 = (self.y1 + sig * r) / (1.0 + sig)
        g = gradient(self.xb, self.shape)
        z = [self.y2[a] + sig * mu * g[a] for a in range(3)]
        norm = dr.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
        shrink = dr.select(norm > bound, bound / dr.maximum(norm, 1e-30), 1.0)
        self.y2 = [z[a] * shrink for a in range(3)]
        dr.eval(self.y1, self.y2)
        kty = self.A.adjoint(self.y1, self.angles) - mu * divergence(self.y2, self.shape)
        x_new = self._clip(self.x - tau * kty)
        self.xb = 2.0 * x_new - self.x
        self.x = x_new
        dr.eval(self.x, self.xb)

    def primal(self, x=None) -> float:
        """1/2 ||A x - b||^2 + lambda TV(x) (x feasible)."""
        x = self.x if x is None else x
        r = self.A.forward(x, self.angles) - self.b
        return 0.5 * _dot(r, r) + self.lam_abs * tv_iso(x, self.shape)

    def dual(self) -> float:
        """-F*(y) - G*(-K^T y) with G the box [0, upper] (``upper`` required), y2 feasible.
        F1*(y1) = 1/2 |y1|^2 + <y1, b>; G*(z) = upper x sum(max(z, 0)) for the box."""
        if self.upper is None or not self.nonneg:
            raise ValueError("the dual value needs the box 0 <= x <= upper (finite upper)")
        kty = self.A.adjoint(self.y1, self.angles) - self.mu * divergence(self.y2, self.shape)
        g_star = self.upper * float(dr.sum(dr.maximum(-kty, 0.0), mode="evaluated")[0])
        return -(0.5 * _dot(self.y1, self.y1) + _dot(self.y1, self.b)) - g_star

    def gap(self) -> float:
        """Primal-dual gap P(x) - D(y) >= 0 (0 at the saddle point)."""
        return self.primal() - self.dual()


def pdhg(proj, geometry: Geometry, angles=None, *, n_iter: int = FIXED_ITERATIONS,
         lam: float = FIXED_LAM, upper=None, gamma: float = DEFAULT_GAMMA,
         nonneg: bool = True, norm_A=None, init=None,
         power_iters: int = 8, progress: bool = True, callback=None) -> np.ndarray:
    """Chambolle-Pock TV reconstruction (see the module docstring).

    Args:
        proj: line integrals [view, v, u] = (len(angles), *nDetector).
        geometry: the scan; ``angles`` (radians) overrides ``geometry.angles``.
        n_iter: iterations (each one forward and one back projection of every view).
        lam: TV weight as a fraction of max(A^T b) (dimensionless, >= 0; 0 = least squares).
        upper: optional upper bound on densities (None: none).
        gamma: sigma ||K||, the primal/dual step balance (sigma tau ||K||^2 = 0.99).
        nonneg: clip negative densities (the constraint x >= 0).
        norm_A: ||A|| if known (skips the power iteration of ``power_iters`` steps).
        init: the starting volume: None / "zeros", "fdk", or a volume [x, y, z] (clipped
            to the box).
        progress: tqdm bar on stderr.
        callback: optional ``f(iteration, volume numpy [x, y, z])`` after every iteration;
            a true return value ends the run.
    Returns:
        float32 [x, y, z] densities.
    """
    a, p = _check_inputs(proj, geometry, angles, n_iter)
    solver = PDHG(p, geometry, a, lam=float(lam), upper=upper, gamma=gamma, norm_A=norm_A,
                  power_iters=power_iters, nonneg=nonneg, init=init)
    with _progress(int(n_iter), "PDHG", progress) as bar:
        for it in range(int(n_iter)):
            solver.step()
            bar.update(1)
            if callback is not None and callback(it, _to_numpy(solver.x, geometry)):
                break
    return _to_numpy(solver.x, geometry)


# ---------------------------------------------------------------- reconstruction contract
def heldout_cap(geometry: Geometry) -> int:
    """The default cap under ``stop="heldout"``: HELDOUT_ITERATION_CAP x (n / 64)^2 for a
    grid whose longest axis has n > 64 voxels, HELDOUT_ITERATION_CAP below. A finer grid
    carries finer detail, which PDHG's fixed-size steps reach in more iterations: at 128^3
    the 64^3 cap stops every candidate while its held-out views still improve."""
    n = max(int(x) for x in geometry.nVoxel)
    return max(HELDOUT_ITERATION_CAP,
               int(round(HELDOUT_ITERATION_CAP * (n / HELDOUT_CAP_SIZE) ** 2)))


def _flag(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"pdhg: {name} must be true or false, got {value!r}")
    return bool(value)


def reconstruct_pdhg(case, *, stop: str = "heldout", n_iter=None, lam=None, gamma=None,
                     lam_rule=None, upper=None, nonneg: bool = True, power_iters: int = 8,
                     eval_every: int = EVAL_EVERY, holdout_every=None, oracle=None,
                     start=None, widen=None, progress: bool = True):
    """The ``--method pdhg`` entry point: Chambolle-Pock TV of ``case.train``.

    Options: stop ("heldout": the iteration count and lam are chosen on held-out views by
    gr's rule, evaluated every ``eval_every`` iterations, then run on all views,
    mi_grg.protocol.heldout; "none": n_iter iterations at one lam), n_iter (cap under
    "heldout", ``heldout_cap``; FIXED_ITERATIONS under "none"), lam (None = LAM_GRID
    under "heldout", FIXED_LAM under "none"; a number, or under "heldout" a list), lam_rule
    (how "heldout" chooses lam from a grid: "one_se", the one-standard-error rule, "best",
    the best held-out PSNR, or "morozov", Morozov's discrepancy principle:
    mi_grg.protocol.search.RULES; None = DEFAULT_LAM_RULE), gamma
    (primal/dual step balance, DEFAULT_GAMMA), upper (None), nonneg (True), power_iters
    (8), eval_every, holdout_every (None = gr's), oracle (None = score iterations when a
    ground truth exists), start (None; or, to refine another method's result under
    "heldout", the volumes [x, y, z] the decision runs and the final run start from:
    ``run_heldout``'s ``start``), widen (under "heldout": the cap n_iter is a base that
    doubles while the held-out PSNR still gains, mi_grg.protocol.widening; None =
    WIDEN_CAP),
    progress. Returns (float32 [x, y, z], info): under "heldout" what was decided, under
    "none" the count and lam and, with a ground truth, the research log's 3-D PSNR every
    ``eval_every`` iterations (``oracle``: it decides nothing); unknown options raise.
    """
    gamma = DEFAULT_GAMMA if gamma is None else float(gamma)
    if lam_rule is not None and lam_rule not in RULES:
        raise ValueError(f"pdhg: lam_rule must be one of {', '.join(RULES)}, got {lam_rule!r}")
    norms = {}

    def run(proj, geo, **kw):
        # ||A|| once per set of views (the candidates share the fitted views' operator)
        key = np.asarray(geo.angles, np.float64).tobytes()
        if key not in norms:
            norms[key] = operator_norm(JosephProjector(geo), geo.angles, power_iters)
        return pdhg(proj, geo, gamma=gamma, upper=upper, nonneg=nonneg, norm_A=norms[key],
                    **kw)

    if _fixed(stop, holdout_every, oracle, "pdhg"):
        if start is not None or lam_rule is not None or widen is not None:
            raise ValueError("pdhg: start (a refinement's start volumes), lam_rule and widen "
                             "need stop='heldout'")
        lm = _one(FIXED_LAM if lam is None else lam, "lam")
        n = FIXED_ITERATIONS if n_iter is None else int(n_iter)
        info = {"protocol": "fixed", "iterations": n, "lam": lm}
        if case.vol_gt is None:
            return run(case.train, case.geometry, n_iter=n, lam=lm, progress=progress), info
        # The research log (decides nothing): 3-D PSNR every eval_every iterations, so a
        # fixed count's result stands beside its best iteration; scoring time excluded.
        curve, spent = [], [0.0]

        def score(it, vol):
            if (it + 1) % eval_every == 0 or it + 1 == n:
                t = time.perf_counter()
                curve.append((it + 1, float(psnr_3d(vol, case.vol_gt))))
                spent[0] += time.perf_counter() - t

        vol = run(case.train, case.geometry, n_iter=n, lam=lm, progress=progress,
                  callback=score)
        return vol, {**info, "oracle": oracle_info(curve, n), "oracle_seconds": spent[0]}
    grid = weight_grid(lam, "lam", LAM_GRID, DEFAULT_LAM_RULE if lam_rule is None else lam_rule)
    if lam_rule is not None and not isinstance(grid, LogGrid):
        raise ValueError(f"pdhg: lam_rule={lam_rule!r} chooses among a grid of lam; lam="
                         f"{lam!r} leaves nothing to choose")
    cap = heldout_cap(case.geometry) if n_iter is None else n_iter
    vol, info = run_heldout(case, run, grid, project=forward_project, name="pdhg",
                            eval_every=eval_every, max_sweeps=cap,
                            holdout_every=holdout_every, oracle=oracle, start=start,
                            widen=WIDEN_CAP if widen is None else _flag(widen, "widen"),
                            progress=progress)
    if "cap" not in info:          # a widening cap records itself
        info["cap"] = {"iterations": int(cap), "binds": info["chosen"]["sweeps"] >= int(cap),
                       "from": "n_iter" if n_iter is not None else
                       f"heldout_cap: {HELDOUT_ITERATION_CAP} x (n / {HELDOUT_CAP_SIZE})^2, n = "
                       f"{max(case.geometry.nVoxel)} (at least {HELDOUT_ITERATION_CAP})"}
    info["norm_A"] = {"fitted_views": norms.get(np.asarray(
        case.geometry.angles, np.float64)[info["decision_views"]].tobytes()),
        "all_views": norms.get(np.asarray(case.geometry.angles, np.float64).tobytes()),
        "power_iterations": int(power_iters)}
    return vol, info
