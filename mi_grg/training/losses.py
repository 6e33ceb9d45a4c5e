"""Training losses in Dr.Jit (differentiable, both variants): L1, D-SSIM, 3-D TV.

All return an ``mi.Float`` of width 1 (a scalar that ``dr.backward`` accepts).

* ``l1``: mean absolute difference (R2-Gaussian ``l1_loss``).
* ``rms``: root mean square difference (least squares' gradient direction; its size does
  not shrink with the residual, as L1's does not).
* ``dssim``: 1 - SSIM with R2-Gaussian's/3DGS's loss SSIM: 11 x 11 Gaussian window,
  sigma 1.5 (the 1-D window normalised to sum 1; the 2-D window its outer product),
  applied like ``conv2d(padding=5)`` -- ZERO padding, same-size map -- with the constants
  C1 = 0.01^2, C2 = 0.03^2 (data range 1; their projections and volumes are in [0, ~1]).
  The SSIM map is averaged over every pixel of every view, the border included. This is
  the same SSIM as ``mi_grg.evaluation.metrics`` (the evaluation metric) but differentiable.
* ``tv_3d``: R2-Gaussian's ``tv_3d_loss``: the SUM of ABSOLUTE forward differences along
  x, y and z, divided (``reduction="mean"``, what their train.py uses) by the number of
  differences, (X-1)YZ + X(Y-1)Z + XY(Z-1).

Images are ``mi.TensorXf`` [view, v, u] (or [v, u] for one view); volumes ``mi.TensorXf``
[x, y, z]. Shifts are gathers on the flat array, so the same code runs on llvm_ad_mono and
cuda_ad_mono; the SSIM blur is a ``dr.CustomOp`` whose adjoint is the blur itself.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.evaluation.metrics import WINDOW_SIGMA, WINDOW_SIZE, gaussian_window_1d

C1 = 0.01 ** 2
C2 = 0.03 ** 2
RMS_FLOOR = 1e-12


def _flat(x, name):
    """(flat mi.Float, shape tuple) of a TensorXf / Float / array-like."""
    if isinstance(x, mi.TensorXf):
        return x.array, tuple(x.shape)
    if isinstance(x, mi.Float):
        return x, (dr.width(x),)
    arr = np.asarray(x, dtype=np.float32)
    return mi.Float(arr.reshape(-1)), arr.shape


def _residual(pred, target, name: str) -> "mi.Float":
    """pred - target, flat (same non-empty shapes; ``name`` for the error)."""
    a, sa = _flat(pred, "pred")
    b, sb = _flat(target, "target")
    if sa != sb:
        raise ValueError(f"pred has shape {sa} but target has shape {sb}")
    if dr.width(a) == 0:
        raise ValueError(f"{name} of empty arrays")
    return a - b


def l1(pred, target) -> "mi.Float":
    """mean |pred - target| over all entries (same shapes)."""
    return dr.mean(dr.abs(_residual(pred, target, "l1")))


def rms(pred, target) -> "mi.Float":
    """sqrt(mean (pred - target)^2 + tiny) over all entries (same shapes); the tiny floor
    (``RMS_FLOOR``) keeps the gradient finite at a zero residual."""
    return dr.sqrt(dr.mean(dr.square(_residual(pred, target, "rms"))) + RMS_FLOOR)


#: ``data_loss`` name -> the view's data term (the names ``config.DATA_LOSSES`` validates).
DATA_TERMS = {"l1": l1, "rms": rms}


def _blur_axis(img, n_views, h, w, weights, axis):
    """1-D correlation with ``weights`` along u (axis=2) or v (axis=1), zero padding.

    img: flat mi.Float of [n_views, h, w] (C order). Unrolled over the taps: one kernel.
    """
    r = len(weights) // 2
    idx = dr.arange(mi.UInt32, n_views * h * w)
    if axis == 2:
        pos, stride, n = mi.Int32(idx % w), 1, w
    else:
        pos, stride, n = mi.Int32((idx // w) % h), w, h
    base = mi.Int32(idx)
    out = dr.zeros(mi.Float, n_views * h * w)
    for k, wk in enumerate(weights):
        off = k - r
        q = pos + off
        active = (q >= 0) & (q < n)
        src = mi.UInt32(dr.select(active, base + off * stride, 0))
        out = dr.fma(dr.gather(mi.Float, img, src, active), wk, out)
    return out


def _blur_plain(img, n_views, h, w, weights):
    rows = _blur_axis(img, n_views, h, w, weights, 2)
    # Evaluate between the passes: gathers from an unevaluated array would recompute the
    # whole first pass for each of the second pass's taps (docs/benchmarks.md).
    dr.eval(rows)
    return _blur_axis(rows, n_views, h, w, weights, 1)


class _GaussianBlur(dr.CustomOp):
    """Separable zero-padded blur with a symmetric kernel. The operator is self-adjoint
    (correlation with a symmetric kernel; zero padding on both sides), so the backward
    pass is the same blur -- gathers only, instead of AD's atomic scatter-adds."""

    def eval(self, img, n_views, h, w, weights):
        self.shape = (n_views, h, w, weights)
        return _blur_plain(img, n_views, h, w, weights)

    def forward(self):
        self.set_grad_out(_blur_plain(self.grad_in("img"), *self.shape))

    def backward(self):
        self.set_grad_in("img", _blur_plain(self.grad_out(), *self.shape))

    def name(self):
        return "GaussianBlur"


def _blur(img, n_views, h, w, weights):
    if dr.grad_enabled(img):
        return dr.custom(_GaussianBlur, img, n_views, h, w, weights)
    return _blur_plain(img, n_views, h, w, weights)


def ssim_map(pred, target, window_size: int = WINDOW_SIZE,
             sigma: float = WINDOW_SIGMA):
    """Per-pixel SSIM (flat mi.Float, [view, v, u] order) and the image shape."""
    a, sa = _flat(pred, "pred")
    b, sb = _flat(target, "target")
    if sa != sb:
        raise ValueError(f"pred has shape {sa} but target has shape {sb}")
    if len(sa) == 2:
        sa = (1, *sa)
    if len(sa) != 3 or min(sa) == 0:
        raise ValueError(f"images must be [view, v, u] or [v, u] and non-empty, got {sb}")
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be odd and >= 1, got {window_size}")
    n, h, w = sa
    wts = [float(x) for x in gaussian_window_1d(window_size, sigma)]
    mu1 = _blur(a, n, h, w, wts)
    mu2 = _blur(b, n, h, w, wts)
    e11 = _blur(a * a, n, h, w, wts)
    e22 = _blur(b * b, n, h, w, wts)
    e12 = _blur(a * b, n, h, w, wts)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    # Denominator >= C1 * C2 > 0 up to rounding of s1 + s2 (>= -eps): no guard needed
    # beyond the constants, exactly as the reference.
    num = (2 * mu12 + C1) * (2 * s12 + C2)
    den = (mu1_sq + mu2_sq + C1) * (s1 + s2 + C2)
    return num / den, (n, h, w)


def ssim(pred, target, window_size: int = WINDOW_SIZE, sigma: float = WINDOW_SIGMA):
    """Mean SSIM over all views and pixels (mi.Float, width 1)."""
    m, _ = ssim_map(pred, target, window_size, sigma)
    return dr.mean(m)


def dssim(pred, target, window_size: int = WINDOW_SIZE, sigma: float = WINDOW_SIGMA):
    """1 - SSIM (R2-Gaussian's ``1.0 - ssim(image, gt_image)``); mi.Float width 1."""
    return 1.0 - ssim(pred, target, window_size, sigma)


def projection_loss(pred, target, lambda_ssim: float, data_loss: str = "l1"):
    """The data term of training: ``data_loss`` ("l1", the paper's, or "rms") + lambda_ssim
    D-SSIM; mi.Float width 1. The D-SSIM blur is skipped when lambda_ssim is 0."""
    if data_loss not in DATA_TERMS:
        raise ValueError(f"data_loss must be one of {', '.join(DATA_TERMS)}, got {data_loss!r}")
    loss = DATA_TERMS[data_loss](pred, target)
    if lambda_ssim > 0:
        loss = loss + lambda_ssim * dssim(pred, target)
    return loss


def tv_3d(vol, reduction: str = "mean") -> "mi.Float":
    """R2-Gaussian's 3-D total variation of a volume [x, y, z] (mi.TensorXf).

    sum |v[i+1,j,k] - v[i,j,k]| + sum |v[i,j+1,k] - v[i,j,k]| + sum |v[i,j,k+1] - v[i,j,k]|,
    divided by the number of differences for ``reduction="mean"`` (default), or not for
    ``"sum"``. Axes of length 1 contribute no differences.
    """
    if reduction not in ("mean", "sum"):
        raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")
    a, shape = _flat(vol, "vol")
    if len(shape) != 3:
        raise ValueError(f"vol must be a 3-D volume [x, y, z], got shape {shape}")
    X, Y, Z = shape
    strides = (Y * Z, Z, 1)
    total = dr.zeros(mi.Float, 1)
    count = 0
    for axis in range(3):
        dims = list(shape)
        dims[axis] -= 1
        m = dims[0] * dims[1] * dims[2]
        if m <= 0:
            continue
        # Flat index of the first voxel of each pair, from the reduced shape's index.
        i = dr.arange(mi.UInt32, m)
        k = i % dims[2]
        j = (i // dims[2]) % dims[1]
        x = i // (dims[2] * dims[1])
        first = x * strides[0] + j * strides[1] + k * strides[2]
        diff = dr.gather(mi.Float, a, first + strides[axis]) - dr.gather(mi.Float, a, first)
        total = total + dr.sum(dr.abs(diff))
        count += m
    if count == 0:
        raise ValueError(f"vol of shape {shape} has no neighbouring voxels")
    return total / count if reduction == "mean" else total
