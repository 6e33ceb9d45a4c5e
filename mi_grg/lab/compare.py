"""Per case, the methods side by side where people compare them: the central z slice of the
ground truth, FDK, the best fairly stopped classical method (by 3-D PSNR among SART,
ASD-POCS and PDHG under every weight rule, and PDHG
from zero at gr's refinement weight), r2 and gr on one grey scale, and their |error|
maps below (one scale too). ``comparison_section`` gives the report's markdown and writes
one PNG per case."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

#: Held-out-stopped classical runs that compete for the "best classical" column.
CLASSICAL_BEST = ("sart", "asd-pocs", "asd-pocs-best", "pdhg", "pdhg-best", "pdhg-morozov",
                  "pdhg-cold")
NAMES = {"fdk": "FDK", "sart": "SART", "asd-pocs": "ASD-POCS",
         "asd-pocs-best": "ASD-POCS (best)", "pdhg": "PDHG", "pdhg-best": "PDHG (best)",
         "pdhg-morozov": "PDHG (Morozov)", "pdhg-cold": "PDHG (cold, gr's weight)",
         "r2": "r2", "gr": "gr"}
#: The |error| maps' scale as a fraction of the ground truth's maximum.
ERROR_FRACTION = 0.25


def _psnr(row):
    v = (row.get("metrics") or {}).get("psnr_3d")
    return None if v is None else float(v)


def pick_runs(rows, case: str) -> list:
    """[(column title, run row)] of ``case``: FDK, the best classical, r2, gr; each only
    when its run finished (metrics.json and vol_pred.npy)."""
    runs = {r["run"]: r for r in rows if r["case"] == case and r.get("metrics")
            and (Path(r["dir"]) / "vol_pred.npy").is_file()}
    picks = [("FDK", runs["fdk"])] if "fdk" in runs else []
    scored = [(_psnr(runs[m]), m) for m in CLASSICAL_BEST if m in runs and _psnr(runs[m])
              is not None]
    if scored:
        _, best = max(scored)
        picks.append((f"best classical: {NAMES[best]}", runs[best]))
    picks += [(NAMES[m], runs[m]) for m in ("r2", "gr") if m in runs]
    return picks


def comparison_figure(out_dir, rows, case: str, png: Path) -> Path | None:
    """Write the case's figure: top row central z slices [x, y] (x right, y up) of the
    ground truth and each picked run on [0, max(ground truth)]; below, |run - ground
    truth| on [0, ERROR_FRACTION * max]. None without a ground truth or runs."""
    gt_path = Path(out_dir) / "data" / case / "vol_gt.npy"
    picks = pick_runs(rows, case)
    if not gt_path.is_file() or not picks:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    gt = np.load(gt_path)
    z = gt.shape[2] // 2
    vmax = float(max(gt.max(), 1e-6))
    n = len(picks) + 1
    fig, axes = plt.subplots(2, n, figsize=(2.3 * n + 1.2, 5.0), squeeze=False,
                             constrained_layout=True)
    grey = axes[0][0].imshow(gt[:, :, z].T, cmap="gray", vmin=0, vmax=vmax, origin="lower")
    axes[0][0].set_title("ground truth", fontsize=9)
    axes[1][0].axis("off")
    err = None
    for j, (title, row) in enumerate(picks, start=1):
        vol = np.load(Path(row["dir"]) / "vol_pred.npy")
        p = _psnr(row)
        axes[0][j].imshow(vol[:, :, z].T, cmap="gray", vmin=0, vmax=vmax, origin="lower")
        axes[0][j].set_title(title + (f"\n{p:.2f} dB" if p is not None else ""), fontsize=9)
        err = axes[1][j].imshow(np.abs(vol[:, :, z] - gt[:, :, z]).T, cmap="magma", vmin=0,
                                vmax=ERROR_FRACTION * vmax, origin="lower")
        axes[1][j].set_title("|error|", fontsize=8)
    for a in axes.ravel():
        a.set_xticks([]), a.set_yticks([])
    fig.colorbar(grey, ax=axes[0, :].tolist(), shrink=0.8, label="density")
    fig.colorbar(err, ax=axes[1, :].tolist(), shrink=0.8, label="|error|")
    fig.suptitle(f"{case}: central z slice (x right, y up), one grey scale", fontsize=10)
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png


def kept_figure(rows, case: str, name: str, img_dir: Path, earlier) -> Path | None:
    """The figure ``name`` of ``case`` as the report in ``earlier`` (its image folder) made
    it, copied into ``img_dir``, where some of the case's runs come from the record (their
    volumes were not kept, so a new figure would lack them) and that figure exists; None
    otherwise (the figure is made anew)."""
    if earlier is None or not any(r.get("recorded") for r in rows or () if r["case"] == case):
        return None
    src = Path(earlier) / name
    if not src.is_file():
        return None
    Path(img_dir).mkdir(parents=True, exist_ok=True)
    return Path(shutil.copyfile(src, Path(img_dir) / name))


def comparison_section(out_dir, rows, img_dir: Path, rel: str, earlier=None) -> list:
    """Markdown lines of the report's "Slices per case" section (Table 1's runs);
    ``earlier``: the image folder of the report this one replaces (``kept_figure``)."""
    md = ["## Slices per case", ""]
    figures, kept = [], []
    for case in sorted({r["case"] for r in rows or []}):
        name = f"compare_{case}.png"
        png = kept_figure(rows, case, name, img_dir, earlier)
        if png is not None:
            kept.append(case)
        else:
            png = comparison_figure(out_dir, rows, case, Path(img_dir) / name)
        if png is not None:
            figures += [f"![{case}]({rel}/{png.name})", ""]
    if not figures:
        return md + ["No case has both a ground truth and a finished run.", ""]
    note = ([f"The figures of {', '.join(kept)} are those of the report that had their runs' "
             "volumes (some of their runs are the record's now).", ""] if kept else [])
    return md + ["Central z slice of each case: ground truth, FDK, the best of SART / "
                 "ASD-POCS / PDHG under either weight rule (held-out stopped, by 3-D PSNR), r2 "
                 "and gr on one grey scale (0 to the ground truth's maximum); below, |error| "
                 "on 0 to "
                 f"{ERROR_FRACTION:g} x that maximum.", ""] + note + figures
