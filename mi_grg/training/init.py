"""De-Init: Gaussians from a (denoised) FDK volume (GR-Gaussian Sec. 3.3.1; R2-Gaussian's
``initialize_pcd.py`` when ``sigma_d`` is None/0).

Steps and the choices made where the paper is silent:

1. Denoise: ``denoise_volume`` applies the paper's normalised Gaussian filter
   f'(i) = 1/Z sum_{j in [-r, r]^3} exp(-|j|^2 / (2 sigma_d^2)) f(i + j), sigma_d in voxels.
   The 3-D kernel is the product of three normalised 1-D kernels (exactly, including Z),
   so it is applied separably: ``scipy.ndimage.gaussian_filter``. Radius
   r = int(4 sigma_d + 0.5) (scipy.ndimage's default ``truncate=4``: the authors' Python
   implementation most plausibly called ``gaussian_filter(vol, sigma_d)``); border
   ``mode="reflect"`` (scipy's default,
   d c b a | a b c d), which neither darkens the border (as zero padding would) nor needs
   knowledge of what lies outside. Both are arguments.
2. Candidates: voxels with denoised value > tau * max(denoised volume). tau = 0.001 is the
   paper's; it is relative to the maximum so that it does not depend on the units of the
   volume (for R2-Gaussian's data, normalised to max ~1, it equals their absolute
   threshold). An empty/non-positive volume raises ``InitError``.
3. Centres: M = min(n_points, #candidates) candidate voxels drawn uniformly WITHOUT
   replacement (R2-Gaussian asserts #candidates >= M; we cap instead, see ``info``), sorted
   by flat index for memory locality. The centre is the voxel centre (``Geometry``
   convention; R2-Gaussian uses ``index * dVoxel - sVoxel / 2``, half a voxel off) plus,
   if ``jitter``, a uniform offset within the voxel (off by default, as R2-Gaussian).
4. Scales (R2-Gaussian ``create_from_pcd``): isotropic, sqrt of the mean SQUARED distance
   to the 3 nearest other centres (simple-knn's ``distCUDA2``), clamped to
   [0.0005, 0.5] x max(sVoxel) -- R2-Gaussian's scale bounds (``scale_min``/``scale_max``),
   whose lower end equals its ``clamp_min(0.001**2)`` in its [-1, 1]^3 units. Fewer than
   4 centres: the available neighbours; a single centre: the largest voxel edge.
5. Rotations: identity.
6. Densities: denoised value at the centre x ``density_rescale``. Why rescale: the field
   is the SUM of all kernels, and neighbouring kernels (spacing ~ their scale) overlap:
   sum_j exp(-|x - p_j|^2 / (2 s^2)) over a lattice of spacing a is ~(2 pi)^{3/2} s^3 / a^3
   -- several times 1 -- so unscaled densities would overshoot the volume by that factor.
   R2-Gaussian (and the paper, which follows it) use the empirical 0.15 (default here).
   For uniformly random centres the 3-NN rule gives scales somewhat below the mean
   spacing, so the kernels overlap several-fold in the interior and fewer times near the
   object's surface, which explains R2-Gaussian's constant (docs/benchmarks.md,
   "Measurements behind defaults").
   ``density_rescale="auto"`` instead picks the factor c minimising
   sum_i (c F_i - v_i)^2, with F_i = sum_j v_j exp(-|p_i - p_j|^2 / (2 s_j^2)) the field
   of the unscaled kernels at the centres and v_i the target values (least squares fit of
   the initial field to the denoised volume at the centres; see ``auto_density_rescale``).
"""
from __future__ import annotations

import math

import numpy as np

from mi_grg.core.gaussians import Gaussians

BORDER_MODES = ("reflect", "nearest", "constant")
SCALE_BOUNDS = (0.0005, 0.5)   # x max(sVoxel); R2-Gaussian's scale_min / scale_max


class InitError(ValueError):
    """Initialisation impossible (empty volume, bad argument); the message says which."""


# ------------------------------------------------------------------ denoising
def default_radius(sigma_d: float) -> int:
    """Window radius r = int(4 sigma + 0.5) (scipy.ndimage.gaussian_filter's truncate=4)."""
    return int(4.0 * float(sigma_d) + 0.5)


def denoise_volume(vol, sigma_d: float | None = 3.0, radius: int | None = None,
                   mode: str = "reflect") -> np.ndarray:
    """The paper's normalised Gaussian filter of a volume [x, y, z] (see module docstring).

    Args:
        vol: volume [x, y, z] (any float array; NaN/Inf rejected).
        sigma_d: filter standard deviation in voxels; None or 0 returns a float32 copy.
        radius: window radius r in voxels; default ``default_radius(sigma_d)``.
        mode: border rule: "reflect" (scipy's; default), "nearest" (edge replicate) or
            "constant" (zeros outside; the weights are NOT renormalised, as in scipy).

    Returns the filtered volume, float32 [x, y, z]: ``scipy.ndimage.gaussian_filter`` (the
    same separable, normalised filter) in float64 on the host. Runs once per training run.
    """
    from scipy.ndimage import gaussian_filter
    v = np.asarray(vol, dtype=np.float32)
    if v.ndim != 3 or v.size == 0:
        raise InitError(f"vol must be a non-empty volume [x, y, z], got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InitError("vol contains NaN or Inf")
    if sigma_d is None or sigma_d == 0:
        return v.copy()
    if not (math.isfinite(sigma_d) and sigma_d > 0):
        raise InitError(f"sigma_d must be > 0 voxels (or None/0 for no filter), got {sigma_d}")
    if mode not in BORDER_MODES:
        raise InitError(f"mode must be one of {BORDER_MODES}, got {mode!r}")
    r = default_radius(sigma_d) if radius is None else int(radius)
    if r < 0:
        raise InitError(f"radius must be >= 0, got {radius}")
    out = gaussian_filter(v.astype(np.float64), float(sigma_d), mode=mode, radius=r)
    return out.astype(np.float32)


def sigma_d_voxels(sigma_d: float, n_voxel, grid: int = 256) -> float:
    """The De-Init filter std in voxels of a grid ``n_voxel`` [x, y, z].

    ``sigma_d`` is given in voxels of a grid ``grid`` voxels along its longest axis: the
    paper tuned sigma_d = 3 on 256^3 volumes, where it blurs over 3/256 of the volume;
    the same 3 voxels on a 64^3 grid blur over 4x that length, and the filtered FDK
    matches the ground truth worse (docs/benchmarks.md, De-Init filter width). ``grid`` = 0
    takes it in the case's own voxels. Returns sigma_d x max(n_voxel) / grid (or sigma_d)."""
    if not (math.isfinite(sigma_d) and sigma_d >= 0):
        raise InitError(f"sigma_d must be >= 0 voxels, got {sigma_d}")
    if int(grid) != grid or grid < 0:
        raise InitError(f"sigma_d_grid must be an integer >= 0 (voxels), got {grid}")
    if grid == 0:
        return float(sigma_d)
    return float(sigma_d) * max(int(n) for n in n_voxel) / int(grid)


# ------------------------------------------------------------------ scales, rescale
def knn_scales(positions: np.ndarray, volume_size: float, voxel_size: float) -> np.ndarray:
    """Isotropic scales [M]: sqrt(mean squared distance to the 3 nearest other points),
    clamped to SCALE_BOUNDS x volume_size (R2-Gaussian's rule; see module docstring)."""
    from scipy.spatial import cKDTree
    p = np.asarray(positions, dtype=np.float64)
    m = p.shape[0]
    if m == 1:
        d = np.array([voxel_size])
    else:
        k = min(3, m - 1)
        dist, _ = cKDTree(p).query(p, k=k + 1)
        d = np.sqrt(np.mean(dist[:, 1:] ** 2, axis=1))   # column 0 is the point itself
    lo, hi = SCALE_BOUNDS
    return np.clip(d, lo * volume_size, hi * volume_size)


def auto_density_rescale(positions: np.ndarray, scales: np.ndarray, values: np.ndarray,
                         n_neighbors: int = 128) -> float:
    """Least-squares factor c so that the field of kernels with densities c * values
    matches ``values`` at the kernel centres (isotropic ``scales`` [M]).

    F_i = sum_j values_j exp(-|p_i - p_j|^2 / (2 s_j^2)) over the ``n_neighbors`` nearest
    centres of p_i (itself included; farther kernels are neglected -- with neighbour
    spacing ~ s they lie beyond ~3 standard deviations, where exp(-9/2) ~ 1 %); c = sum v F / sum F^2.
    """
    from scipy.spatial import cKDTree
    p = np.asarray(positions, dtype=np.float64)
    s = np.asarray(scales, dtype=np.float64).reshape(-1)
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    k = min(int(n_neighbors), p.shape[0])
    dist, nb = cKDTree(p).query(p, k=k)
    dist, nb = dist.reshape(p.shape[0], k), nb.reshape(p.shape[0], k)
    field = np.sum(v[nb] * np.exp(-0.5 * (dist / s[nb]) ** 2), axis=1)
    den = float(np.sum(field * field))
    if not den > 0:
        raise InitError("cannot derive a density rescale: the initial field is zero")
    return float(np.sum(v * field) / den)


# ------------------------------------------------------------------ De-Init
def init_gaussians(vol, geometry, n_points: int = 50000, tau: float = 0.001,
                   sigma_d: float | None = 3.0, density_rescale: float | str = 0.15,
                   seed: int = 0, jitter: bool = False, radius: int | None = None,
                   mode: str = "reflect", info: dict | None = None) -> Gaussians:
    """Initial Gaussians from a reconstruction ``vol`` [x, y, z] (e.g. FDK) on ``geometry``.

    Args:
        vol: volume [x, y, z], shape ``geometry.nVoxel``, in density units.
        geometry: ``mi_grg.Geometry`` (voxel centres, sizes).
        n_points: M, the number of Gaussians (capped by the number of candidates).
        tau: candidate threshold as a fraction of the denoised volume's maximum.
        sigma_d: denoising filter std in voxels; None/0: plain FDK init (R2-Gaussian).
        density_rescale: factor on the sampled values (0.15, R2-Gaussian's), or "auto"
            (``auto_density_rescale``).
        seed: NumPy seed for the sampling (and jitter); same seed, same Gaussians.
        jitter: offset each centre uniformly within its voxel.
        radius, mode: passed to ``denoise_volume``.
        info: optional dict, filled with n_candidates, n_points, threshold, rescale,
            capped.

    Returns ``Gaussians`` with M kernels (identity rotations).
    """
    v = np.asarray(vol)
    if v.shape != tuple(geometry.nVoxel):
        raise InitError(f"vol has shape {v.shape}, expected nVoxel [x, y, z] = "
                        f"{tuple(geometry.nVoxel)}")
    if int(n_points) < 1:
        raise InitError(f"n_points must be >= 1, got {n_points}")
    if not (math.isfinite(tau) and 0 <= tau < 1):
        raise InitError(f"tau must lie in [0, 1) (fraction of the volume maximum), got {tau}")
    if not (density_rescale == "auto" or (isinstance(density_rescale, (int, float))
                                          and math.isfinite(density_rescale)
                                          and density_rescale > 0)):
        raise InitError(f"density_rescale must be > 0 or 'auto', got {density_rescale!r}")
    den = denoise_volume(v, sigma_d, radius=radius, mode=mode)
    vmax = float(den.max())
    if not vmax > 0:
        raise InitError(
            f"the {'denoised ' if sigma_d else ''}volume has no positive voxel (max "
            f"{vmax:.3g}): nothing to initialise from; check the reconstruction")
    threshold = tau * vmax
    cand = np.flatnonzero(den.reshape(-1) > threshold)
    m = min(int(n_points), cand.size)   # cand.size >= 1: the maximum voxel exceeds it
    rng = np.random.default_rng(seed)
    chosen = np.sort(cand[rng.choice(cand.size, size=m, replace=False)])
    ijk = np.stack(np.unravel_index(chosen, den.shape), axis=-1)
    axes = geometry.voxel_axes()
    pos = np.stack([axes[a][ijk[:, a]] for a in range(3)], axis=-1)
    if jitter:
        pos = pos + (rng.random((m, 3)) - 0.5) * np.asarray(geometry.dVoxel)
    values = den.reshape(-1)[chosen].astype(np.float64)
    scales = knn_scales(pos, max(geometry.sVoxel), max(geometry.dVoxel))
    if density_rescale == "auto":
        rescale = auto_density_rescale(pos, scales, values)
    else:
        rescale = float(density_rescale)
    if info is not None:
        info.update(n_candidates=int(cand.size), n_points=int(m), threshold=threshold,
                    rescale=rescale, capped=bool(m < int(n_points)))
    return Gaussians.from_numpy(pos, np.repeat(scales[:, None], 3, axis=1),
                                None, values * rescale)
