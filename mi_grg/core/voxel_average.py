"""Gaussians whose values at the voxel centres are their averages over the voxels.

The ground truth of a CT volume is a voxel average (a detector pixel and a voxel both
integrate), but ``voxelize`` samples the field at voxel centres: a trained field with
structure finer than a voxel aliases there. Averaging a Gaussian over a box of sides
h = (hx, hy, hz) is, to second order, convolving it with a Gaussian of covariance
diag(h^2 / 12); a sum of Gaussians stays a sum of Gaussians under that, so the averaged
field is a plain field that every export, renderer and cross-check reads as it is.

    Sigma' = Sigma + f diag(h^2 / 12),   rho' = rho sqrt(det Sigma / det Sigma')

keeps each Gaussian's mass (its line integrals through the whole volume change only by
the blur). ``f`` in [0, 1] is the share of the box's variance added: 1 is the box's own
second moment; a box's tails are shorter than a Gaussian's, so the best share on the
tuning cases is below 1 (docs/benchmarks.md, "The field's result").
"""
from __future__ import annotations

import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry


def voxel_variance(geometry: Geometry, fraction: float) -> np.ndarray:
    """``fraction`` x h^2 / 12 per axis [x, y, z] (length units squared), h the voxel size."""
    if not (np.isfinite(fraction) and 0.0 <= fraction <= 1.0):
        raise ValueError(f"voxel_average must be a number in [0, 1], got {fraction!r}")
    h = np.asarray(geometry.sVoxel, np.float64) / np.asarray(geometry.nVoxel, np.float64)
    return fraction * h * h / 12.0


def convolve_gaussians(g: Gaussians, variance) -> Gaussians:
    """Each Gaussian of ``g`` convolved with a centred Gaussian of covariance
    diag(``variance``) [x, y, z], its mass kept (module docstring)."""
    v = np.asarray(variance, np.float64).reshape(3)
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError(f"variance must be 3 finite numbers >= 0, got {variance!r}")
    a = g.numpy()
    if len(g) == 0 or not np.any(v > 0):
        return g
    s = a["scales"].astype(np.float64)
    q = a["rotations"].astype(np.float64)
    if np.ptp(v) <= 1e-12 * v.max():
        # isotropic: the principal axes stay, each variance grows by v
        s2 = np.sqrt(s * s + v[0])
        rot = q
    else:
        R = _matrices(q)
        cov = np.einsum("nik,nk,njk->nij", R, s * s, R) + np.diag(v)
        lam, Q = np.linalg.eigh(cov)
        Q[np.linalg.det(Q) < 0, :, 2] *= -1.0        # a rotation, not a reflection
        s2, rot = np.sqrt(lam), _quaternions(Q)
    rho = a["densities"].astype(np.float64) * np.prod(s / s2, axis=1)
    return Gaussians.from_numpy(a["positions"], s2.astype(np.float32),
                                rot.astype(np.float32), rho.astype(np.float32))


def voxel_average(g: Gaussians, geometry: Geometry, fraction: float) -> Gaussians:
    """``g`` averaged over ``geometry``'s voxels at ``fraction`` of the box variance."""
    return convolve_gaussians(g, voxel_variance(geometry, fraction))


def _matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] of quaternions (w, x, y, z) [N, 4]."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)],
        axis=1)


def _quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) [N, 4] of rotation matrices [N, 3, 3] (Shepperd's
    method: the largest of the four candidates' squares avoids a division by ~0)."""
    t = np.stack([R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2], R[:, 0, 0], R[:, 1, 1],
                  R[:, 2, 2]], -1)
    k = np.argmax(t, axis=1)
    q = np.empty((len(R), 4))
    for case in range(4):
        m = k == case
        r = R[m]
        if case == 0:
            w = 0.5 * np.sqrt(1 + t[m, 0])
            q[m] = np.stack([w, (r[:, 2, 1] - r[:, 1, 2]) / (4 * w),
                             (r[:, 0, 2] - r[:, 2, 0]) / (4 * w),
                             (r[:, 1, 0] - r[:, 0, 1]) / (4 * w)], -1)
            continue
        i = case - 1
        j, l = (i + 1) % 3, (i + 2) % 3
        d = 0.5 * np.sqrt(np.maximum(1 + 2 * r[:, i, i] - t[m, 0], 0.0))
        e = np.empty((int(m.sum()), 4))
        e[:, 0] = (r[:, l, j] - r[:, j, l]) / (4 * d)
        e[:, 1 + i] = d
        e[:, 1 + j] = (r[:, j, i] + r[:, i, j]) / (4 * d)
        e[:, 1 + l] = (r[:, l, i] + r[:, i, l]) / (4 * d)
        q[m] = e
    return q / np.linalg.norm(q, axis=1, keepdims=True)
