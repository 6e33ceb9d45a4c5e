"""Figures people would rather look at than read: orthogonal slice montages."""
from __future__ import annotations

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
