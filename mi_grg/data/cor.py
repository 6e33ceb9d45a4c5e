"""Centre of rotation of a circular scan, from its projections (``mi-grg import --cor auto``)."""
from __future__ import annotations

import numpy as np

from mi_grg.data.dataset import DatasetError


def symmetry_centre(profile: np.ndarray) -> float:
    """The continuous column (pixel centres at i + 0.5) about which ``profile`` [u] is most
    symmetric: least squares over candidate centres, linear interpolation, parabolic
    refinement of the best one."""
    nu = profile.size
    x = np.arange(nu) + 0.5
    t = np.arange(0.0, nu / 2, 0.5)

    def cost(c):
        # only pairs that both fall on the detector: a truncated side says nothing
        tt = t[t <= min(c - 0.5, nu - 0.5 - c)]
        a = np.interp(c + tt, x, profile)
        b = np.interp(c - tt, x, profile)
        return float(np.mean((a - b) ** 2))

    grid = np.arange(nu * 0.25, nu * 0.75, 0.05)
    costs = np.array([cost(c) for c in grid])
    i = int(np.clip(np.argmin(costs), 1, grid.size - 2))
    y0, y1, y2 = costs[i - 1:i + 2]
    den = y0 - 2 * y1 + y2
    shift = 0.5 * (y0 - y2) / den if den > 0 else 0.0
    return float(grid[i] + np.clip(shift, -1, 1) * 0.05)


def estimate_cor(proj: np.ndarray, angles: np.ndarray) -> tuple:
    """Column (continuous, pixel centres at i + 0.5) onto which the rotation axis projects,
    and an uncertainty (pixels), from line integrals [view, v, u] of a full-circle scan.

    Every line is measured twice in a 360-degree scan (the conjugate ray of column u at
    view a is column -u at view a + pi + 2 gamma), so the sum over views of the
    projections is symmetric about the axis' column (exactly in the mid-plane, nearly in
    the other rows). The uncertainty is half the spread of the estimates from the even and
    odd views and from the upper and lower rows, at least 0.05 pixel."""
    a = np.sort(np.mod(angles, 2 * np.pi))
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
    if a.size < 8 or gaps.max() > 4 * np.median(gaps) or gaps.max() > np.deg2rad(30):
        raise DatasetError("--cor auto needs a full 360-degree scan with evenly spread "
                             "views (largest angular gap "
                             f"{np.degrees(gaps.max()):.1f} degrees); give --cor PIXELS")
    c = symmetry_centre(proj.sum(axis=(0, 1)))
    nv = proj.shape[1]
    parts = [symmetry_centre(proj[0::2].sum(axis=(0, 1))),
             symmetry_centre(proj[1::2].sum(axis=(0, 1)))]
    if nv >= 4:
        parts += [symmetry_centre(proj[:, :nv // 2].sum(axis=(0, 1))),
                  symmetry_centre(proj[:, nv // 2:].sum(axis=(0, 1)))]
    return c, max(0.05, 0.5 * (max(parts) - min(parts)))
