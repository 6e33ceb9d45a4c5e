"""The training log: one row per iteration, written as ``train_log.csv``.

Rows are dicts with the keys of ``LOG_FIELDS`` (``heldout_psnr`` and ``psnr_3d`` only at
the iterations that evaluate them); ``mi_grg.evaluation.plotting.plot_log`` draws them.
"""
from __future__ import annotations

import csv

LOG_FIELDS = ("iteration", "seconds", "loss", "heldout_psnr", "psnr_3d", "n_gaussians")


def write_log(path, log: list) -> None:
    """Write ``log`` (list of row dicts) as CSV with the columns ``LOG_FIELDS`` (missing
    entries empty)."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=LOG_FIELDS)
        w.writeheader()
        for row in log:
            w.writerow({k: row.get(k, "") for k in LOG_FIELDS})
