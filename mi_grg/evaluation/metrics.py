"""Image metrics exactly as R2-Gaussian (and GR-Gaussian, which reuses its code) report them.

Reference: R2-Gaussian ``r2_gaussian/utils/image_utils.py`` (``metric_vol``, ``metric_proj``)
and ``r2_gaussian/utils/loss_utils.py`` (``ssim``). Reproduced in float64 NumPy/SciPy:

* PSNR of a volume: ``10 log10(data_range^2 / MSE)`` over the whole volume
  (their ``pixel_max`` = 1.0 by default). Identical inputs give +inf, as theirs does.
* SSIM of an image: 11 x 11 Gaussian window (sigma 1.5, normalised to sum 1), applied like
  ``conv2d(padding=5)``, i.e. ZERO padding and a same-size map; the map is averaged over all
  pixels, the border included. Their ``ssim`` takes no data range: it hard-codes
  ``C1 = 0.01**2`` and ``C2 = 0.03**2``, i.e. data_range = 1 (their volumes lie in [0, 1]).
  ``data_range`` here generalises that as ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2``; the
  default 1.0 is their metric.
* SSIM of a volume: for each axis x, y, z, the mean of the 2-D SSIM over the slices whose
  GROUND-TRUTH slice has ``max() > 0`` (other slices are skipped); the result is the mean
  of the three per-axis values.
* Projection metrics (their ``metric_proj`` on images stacked [v, u, view]): per view whose
  ground truth has ``max() > 0``, the ground truth is divided by ITS maximum and the
  prediction by ITS OWN maximum; then PSNR (peak 1) or SSIM (data range 1); the mean over
  the counted views.

Differences from the reference, all deliberate: float64 instead of float32 (results agree to
~1e-6); no GPU/torch; inputs with NaN/Inf or mismatched shapes are rejected; where theirs
would divide 0 by 0 (no non-empty ground-truth slice/view) we raise; a predicted projection
whose maximum is <= 0 (theirs gives NaN) is left unnormalised, with a warning.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.ndimage import correlate1d

WINDOW_SIZE = 11
WINDOW_SIGMA = 1.5
K1, K2 = 0.01, 0.03
_CHUNK_PIXELS = 1 << 22   # slices per SSIM batch: bounds memory to ~10 arrays of 4M float64


def gaussian_window_1d(size: int = WINDOW_SIZE, sigma: float = WINDOW_SIGMA) -> np.ndarray:
    """Their 1-D window: exp(-(x - size//2)^2 / (2 sigma^2)), normalised to sum 1 (float64).
    The one definition: the training loss's SSIM (``mi_grg.training.losses``) uses it too."""
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-x * x / (2.0 * sigma * sigma))
    return g / g.sum()


# ---------------------------------------------------------------- validation
def _check_pair(pred, gt, ndim, what, pred_name="pred", gt_name="gt"):
    a = np.asarray(pred)
    b = np.asarray(gt)
    for name, arr in ((pred_name, a), (gt_name, b)):
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise ValueError(f"{name} must be a numeric array {what}, got dtype {arr.dtype}")
        if arr.ndim != ndim:
            raise ValueError(f"{name} must be {ndim}-D {what}, got shape {arr.shape}")
        if arr.size == 0:
            raise ValueError(f"{name} is empty (shape {arr.shape}), expected {what}")
    if a.shape != b.shape:
        raise ValueError(f"{pred_name} {what} has shape {a.shape} but {gt_name} has shape "
                         f"{b.shape}; they must match")
    a = a.astype(np.float64, copy=False)
    b = b.astype(np.float64, copy=False)
    for name, arr in ((pred_name, a), (gt_name, b)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or Inf ({np.count_nonzero(~np.isfinite(arr))}"
                             " entries)")
    return a, b


def _check_range(data_range):
    try:
        L = float(data_range)
    except (TypeError, ValueError):
        raise ValueError(f"data_range must be a positive number, got {data_range!r}") from None
    if not math.isfinite(L) or L <= 0:
        raise ValueError(f"data_range must be finite and > 0, got {data_range!r}")
    return L


# ---------------------------------------------------------------- core
def _psnr_from_mse(mse, peak):
    with np.errstate(divide="ignore"):   # mse == 0 -> +inf, as in the reference
        return 10.0 * np.log10(peak * peak / np.asarray(mse, np.float64))


def _ssim_maps(x, y, L):
    """SSIM maps of stacks x, y [n, h, w] (float64) -> [n, h, w]."""
    win = gaussian_window_1d()
    c1, c2 = (K1 * L) ** 2, (K2 * L) ** 2

    def blur(img):
        # The 2-D window is separable; zero padding = conv2d(padding=size//2).
        img = correlate1d(img, win, axis=1, mode="constant", cval=0.0)
        return correlate1d(img, win, axis=2, mode="constant", cval=0.0)

    mu1, mu2 = blur(x), blur(y)
    mu11, mu22, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s11 = blur(x * x) - mu11
    s22 = blur(y * y) - mu22
    s12 = blur(x * y) - mu12
    return ((2 * mu12 + c1) * (2 * s12 + c2)) / ((mu11 + mu22 + c1) * (s11 + s22 + c2))


def _ssim_stack(a, b, L, index=None):
    """Mean SSIM of the 2-D images a[i], b[i] of stacks [n, h, w] (float64) for i in
    ``index`` (default: all) -> [len(index)]. Works in batches to bound memory."""
    index = np.arange(a.shape[0]) if index is None else np.asarray(index)
    out = np.empty(index.size)
    step = max(1, _CHUNK_PIXELS // (a.shape[1] * a.shape[2]))
    for s in range(0, index.size, step):
        sel = index[s:s + step]
        out[s:s + step] = _ssim_maps(a[sel], b[sel], L).mean(axis=(1, 2))
    return out


# ---------------------------------------------------------------- public: 2-D
def ssim_map_2d(img1, img2, data_range: float = 1.0) -> np.ndarray:
    """The per-pixel SSIM map [h, w] that ``ssim_2d`` averages (zero-padded, same size)."""
    a, b = _check_pair(img1, img2, 2, "[h, w]", "img1", "img2")
    return _ssim_maps(a[None], b[None], _check_range(data_range))[0]


def ssim_2d(img1, img2, data_range: float = 1.0) -> float:
    """SSIM of two images [h, w] (R2-Gaussian's ``ssim``; symmetric in its arguments).

    11 x 11 Gaussian window (sigma 1.5), zero padding, mean over the whole same-size map;
    C1 = (0.01 data_range)^2, C2 = (0.03 data_range)^2. data_range = 1 is the reference.
    """
    a, b = _check_pair(img1, img2, 2, "[h, w]", "img1", "img2")
    return float(_ssim_stack(a[None], b[None], _check_range(data_range))[0])


# ---------------------------------------------------------------- public: volumes
def psnr_3d(pred, gt, data_range: float = 1.0) -> float:
    """PSNR (dB) of a volume [x, y, z] over all voxels: 10 log10(data_range^2 / MSE).

    data_range is R2-Gaussian's ``pixel_max`` (1.0 for their [0, 1] densities); +inf when
    pred == gt.
    """
    a, b = _check_pair(pred, gt, 3, "volume [x, y, z]")
    return float(_psnr_from_mse(np.mean((a - b) ** 2), _check_range(data_range)))


def ssim_3d_axes(pred, gt, data_range: float = 1.0) -> tuple:
    """Per-axis SSIM (x, y, z) of a volume [x, y, z]: for each axis, the mean 2-D SSIM over
    the slices whose ground-truth slice has max() > 0 (R2-Gaussian's ``ssim_3d_x/y/z``)."""
    a, b = _check_pair(pred, gt, 3, "volume [x, y, z]")
    L = _check_range(data_range)
    result = []
    for axis, name in enumerate("xyz"):
        keep = np.moveaxis(b, axis, 0).max(axis=(1, 2)) > 0   # their `slice1.max() > 0`
        if not np.any(keep):
            raise ValueError(f"gt has no slice with max > 0 along {name}; SSIM is undefined")
        result.append(float(np.mean(_ssim_stack(np.moveaxis(a, axis, 0),
                                                np.moveaxis(b, axis, 0), L,
                                                np.flatnonzero(keep)))))
    return tuple(result)


def ssim_3d(pred, gt, data_range: float = 1.0) -> float:
    """SSIM of a volume [x, y, z]: mean over x, y, z of ``ssim_3d_axes`` (R2-Gaussian's
    ``metric_vol(gt, pred, "ssim")``)."""
    return float(np.mean(ssim_3d_axes(pred, gt, data_range)))


# ---------------------------------------------------------------- public: projections
def _normalised_views(pred, gt):
    """(pred_n, gt_n, keep): views with gt max > 0, each divided by its own maximum."""
    a, b = _check_pair(pred, gt, 3, "projections [view, v, u]")
    gmax = b.max(axis=(1, 2))
    keep = gmax > 0
    if not np.any(keep):
        raise ValueError("gt has no projection with max > 0; projection metrics are undefined")
    pmax = a.max(axis=(1, 2))
    bad = keep & (pmax <= 0)
    if np.any(bad):
        warnings.warn(f"pred views {np.flatnonzero(bad).tolist()} have max <= 0; left "
                      "unnormalised (the reference would give NaN)", RuntimeWarning,
                      stacklevel=3)
    pscale = np.where(pmax > 0, pmax, 1.0)
    gn = b[keep] / gmax[keep, None, None]
    pn = a[keep] / pscale[keep, None, None]
    return pn, gn, keep


def psnr_proj_views(pred, gt) -> np.ndarray:
    """Per-view PSNR (dB) of projections [view, v, u] after per-view max normalisation
    (peak 1); NaN for views skipped because their ground truth has max <= 0."""
    pn, gn, keep = _normalised_views(pred, gt)
    out = np.full(keep.shape, np.nan)
    out[keep] = _psnr_from_mse(np.mean((pn - gn) ** 2, axis=(1, 2)), 1.0)
    return out


def ssim_proj_views(pred, gt) -> np.ndarray:
    """Per-view SSIM of projections [view, v, u] after per-view max normalisation
    (data range 1); NaN for views skipped because their ground truth has max <= 0."""
    pn, gn, keep = _normalised_views(pred, gt)
    out = np.full(keep.shape, np.nan)
    out[keep] = _ssim_stack(pn, gn, 1.0)
    return out


def psnr_proj(pred, gt) -> float:
    """Mean per-view PSNR (dB) of projections [view, v, u] (R2-Gaussian's ``psnr_2d``)."""
    return float(np.nanmean(psnr_proj_views(pred, gt)))


def ssim_proj(pred, gt) -> float:
    """Mean per-view SSIM of projections [view, v, u] (R2-Gaussian's ``ssim_2d``)."""
    return float(np.nanmean(ssim_proj_views(pred, gt)))


# ---------------------------------------------------------------- report
def metric_report(vol_pred=None, vol_gt=None, proj_pred=None, proj_gt=None,
                  data_range: float = 1.0) -> dict:
    """The metrics R2-Gaussian writes, under its key names (psnr_3d, ssim_3d, ssim_3d_x/y/z,
    psnr_2d, ssim_2d), for whichever pairs are given (volumes [x, y, z], projections
    [view, v, u]). Values are plain floats (PSNR may be inf)."""
    out = {}
    if (vol_pred is None) != (vol_gt is None):
        raise ValueError("give both vol_pred and vol_gt, or neither")
    if (proj_pred is None) != (proj_gt is None):
        raise ValueError("give both proj_pred and proj_gt, or neither")
    if vol_gt is not None:
        out["psnr_3d"] = psnr_3d(vol_pred, vol_gt, data_range)
        sx, sy, sz = ssim_3d_axes(vol_pred, vol_gt, data_range)
        out.update(ssim_3d=float(np.mean([sx, sy, sz])), ssim_3d_x=sx, ssim_3d_y=sy,
                   ssim_3d_z=sz)
    if proj_gt is not None:
        out["psnr_2d"] = psnr_proj(proj_pred, proj_gt)
        out["ssim_2d"] = ssim_proj(proj_pred, proj_gt)
    return out
