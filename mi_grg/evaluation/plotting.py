"""Figures people would rather look at than read: orthogonal slice montages."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _agg():
    import matplotlib
    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt
    return plt


def central_slices(vol: np.ndarray) -> list:
    """The three central orthogonal slices of a volume [x, y, z]: (x=mid) [y, z],
    (y=mid) [x, z], (z=mid) [x, y]."""
    nx, ny, nz = vol.shape
    return [vol[nx // 2, :, :], vol[:, ny // 2, :], vol[:, :, nz // 2]]


def slice_montage(path, pred: np.ndarray, gt: np.ndarray | None = None, title: str = "",
                  vmax: float | None = None) -> None:
    """Write a PNG montage: rows prediction, ground truth, |error| (the last two only with a
    ground truth); columns the central x, y and z slices. Volumes are [x, y, z]."""
    plt = _agg()
    rows = [("prediction", pred)]
    if gt is not None:
        rows += [("ground truth", gt), ("|error|", np.abs(pred - gt))]
    if vmax is None:
        vmax = float(max(np.max(gt) if gt is not None else 0.0, np.percentile(pred, 99.9), 1e-6))
    names = ("x = mid  [y, z]", "y = mid  [x, z]", "z = mid  [x, y]")
    fig, axes = plt.subplots(len(rows), 3, figsize=(9, 3 * len(rows)), squeeze=False)
    for r, (label, vol) in enumerate(rows):
        is_err = label.startswith("|")
        for c, sl in enumerate(central_slices(vol)):
            ax = axes[r][c]
            # Slices are shown with their first index down the rows (array order, no flips).
            im = ax.imshow(sl, cmap="magma" if is_err else "gray", vmin=0,
                           vmax=(vmax * 0.25 if is_err else vmax), interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(names[c], fontsize=9)
            if c == 0:
                ax.set_ylabel(label)
        fig.colorbar(im, ax=axes[r].tolist(), shrink=0.8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def crosscheck_figure(path, mc: np.ndarray, ref: np.ndarray, z: np.ndarray, result: dict,
                      z_range: float = 4.0) -> None:
    """Write the path-traced cross-check as a PNG: one row per view [view, v, u], columns
    volpath transmittance, reference transmittance (one grey scale from the darkest
    pixel to 1) and ``z`` = (volpath - reference) / standard error per pixel (clipped to
    +-``z_range``). Titles carry the numbers of ``result["views"]`` and the verdict."""
    plt = _agg()
    n = mc.shape[0]
    fig, axes = plt.subplots(n, 3, figsize=(10.5, 2.9 * n + 0.9), squeeze=False,
                             layout="constrained")
    lo = float(min(np.min(ref), np.percentile(mc, 1)))
    lo = min(lo, 0.9)     # a nearly transparent object still gets some contrast
    for k in range(n):
        v = result["views"][k]
        verdict = "PASS" if v["pass"] else "FAIL"
        ax = axes[k]
        im0 = ax[0].imshow(mc[k], cmap="gray", vmin=lo, vmax=1, interpolation="nearest")
        ax[1].imshow(ref[k], cmap="gray", vmin=lo, vmax=1, interpolation="nearest")
        im2 = ax[2].imshow(np.clip(z[k], -z_range, z_range), cmap="RdBu_r", vmin=-z_range,
                           vmax=z_range, interpolation="nearest")
        ax[0].set_title(f"view {k} ({v['angle_deg']:.1f} deg): volpath, {result['spp']} spp",
                        fontsize=9)
        short = {"ct_phantom": "exp(-phantom line integral)", "gaussian_medium":
                 "exp(-projector)", "heterogeneous": "exp(-grid line integral)"}
        ax[1].set_title(f"reference T = {short.get(result['object'], result['object'])}",
                        fontsize=9)
        ax[2].set_title(f"{verdict}: z = {v['z']:+.2f}, RMS diff {v['rms_difference']:.4f}\n"
                        f"(expected {v['expected_rms_standard_error']:.4f}), max "
                        f"{v['max_abs_difference']:.3f}", fontsize=9,
                        color="black" if v["pass"] else "red")
        for a in ax:
            a.set_xticks([]), a.set_yticks([])
        fig.colorbar(im0, ax=ax[:2].tolist(), shrink=0.8, label="transmittance I/I0")
        fig.colorbar(im2, ax=ax[2], shrink=0.8, label="(volpath - ref) / SE")
    verdict = "PASS" if result["pass"] else "FAIL"
    what = f"run {result['run']}" if result.get("run") else Path(result["scene"]).name
    fig.suptitle(f"{verdict}: volpath vs {result['reference']}\n{what}, "
                 f"{result['confidence']:.1%} confidence per view (|z| <= "
                 f"{result['z_critical']:.2f}, no improbable pixel)", fontsize=10,
                 color="black" if result["pass"] else "red")
    fig.savefig(path, dpi=90)
    plt.close(fig)
