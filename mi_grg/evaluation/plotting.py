"""Figures people would rather look at than read: orthogonal slice montages, the
training log (loss, PSNR, Gaussian count per iteration) and the path-traced cross-check."""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: Iterations averaged in the loss plot's smoothed curve.
LOSS_PLOT_WINDOW = 25


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


def plot_log(path, log: list, kept_iteration: int | None = None) -> None:
    """Loss, held-out PSNR (and 3-D PSNR when known) and Gaussian count per iteration of a
    training log (``mi_grg.training.log``); ``kept_iteration`` marks the state the run kept."""
    plt = _agg()
    it = [r["iteration"] for r in log]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.4))
    loss = np.asarray([r["loss"] for r in log], np.float64)
    ax[0].semilogy(it, loss, lw=0.5, color="0.75", label="per iteration")
    w = min(LOSS_PLOT_WINDOW, len(loss))
    if w > 1:   # the mean over a window: the TV term enters every tv_every-th iteration only
        ax[0].semilogy(it[w - 1:], np.convolve(loss, np.ones(w) / w, mode="valid"), lw=1.0,
                       color="tab:blue", label=f"mean of {w}")
        ax[0].legend(loc="upper right", fontsize=8)
    ax[0].set_title("training loss")
    ev = [r for r in log if r.get("heldout_psnr") not in (None, "")]
    if ev:
        ax[1].plot([r["iteration"] for r in ev], [r["heldout_psnr"] for r in ev], "o-",
                   label="held-out views (2-D)")
    ev3 = [r for r in log if r.get("psnr_3d") not in (None, "")]
    if ev3:
        ax1b = ax[1].twinx()
        ax1b.plot([r["iteration"] for r in ev3], [r["psnr_3d"] for r in ev3], "s--",
                  color="tab:red", label="3-D vs ground truth")
        ax1b.set_ylabel("3-D PSNR (dB)", color="tab:red")
    if kept_iteration is not None:
        ax[1].axvline(kept_iteration, color="k", ls=":", label="kept state")
    ax[1].set_title("PSNR (dB)")
    if ax[1].get_legend_handles_labels()[0]:
        ax[1].legend(loc="lower right", fontsize=8)
    ax[2].plot(it, [r["n_gaussians"] for r in log], lw=0.8)
    ax[2].set_title("Gaussians")
    for a in ax:
        a.set_xlabel("iteration")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
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
