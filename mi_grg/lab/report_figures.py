"""The results report's figures (and the tables read off them): held-out and 3-D PSNR
per iteration with the replayed stop rule, time-quality curves and the any-time table,
the view counts, the slice montages."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from mi_grg.lab.report_tables import (_heldout, BUDGETS, _cases, CLASSICAL, DASH, _fmt, _index,
                                      _mean_all, METHOD_NAMES, METHOD_ORDER, _value)
from mi_grg.protocol.early_stop import replay


# ---------------------------------------------------------------------------- plots
def _plt():
    from mi_grg.evaluation.plotting import _agg
    return _agg()


def _read_csv(path: Path) -> list:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _col(rows, key):
    out = []
    for r in rows:
        v = r.get(key, "")
        out.append(float(v) if v not in ("", None) else None)
    return out


def plot_iterations(rows, img_dir: Path) -> list:
    """Per case: held-out PSNR and 3-D PSNR vs iteration; returns [(case, png, facts)]."""
    plt = _plt()
    out = []
    idx = _index(rows)
    for case, _ in _cases(rows):
        runs = [r for r in rows if r["case"] == case and r.get("metrics")]
        if not runs:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        ax2 = ax.twinx()
        facts = []
        any3d = False
        for r in runs:
            log = _read_csv(Path(r["dir"]) / "train_log.csv")
            ev = [x for x in log if x.get("heldout_psnr") not in ("", None)]
            if not ev:
                continue
            it = _col(ev, "iteration")
            ho = _col(ev, "heldout_psnr")
            ls = "-" if r["run"].endswith("nostop") else "--"
            ax.plot(it, ho, ls, marker="o", ms=3, label=f"held-out views, {r['label']}")
            p3 = [(i, v) for i, v in zip(_col(ev, "iteration"), _col(ev, "psnr_3d"))
                  if v is not None]
            if p3:
                any3d = True
                ax2.plot(*zip(*p3), ls, color="tab:red", marker="s", ms=3,
                         label=f"3-D vs ground truth, {r['label']}")
            info = r["metrics"].get("method_info") or {}
            if r["run"].endswith("nostop"):
                start = (info.get("schedule") or {}).get("densify_stop", 0)
                stop_it, best_it = replay(it, ho, start=start)
                if stop_it is not None:
                    ax.axvline(stop_it, color="k", ls=":", lw=1)
                    ax.annotate("early stop (replayed)", (stop_it, ax.get_ylim()[0]),
                                rotation=90, fontsize=7, va="bottom", ha="right")
                facts.append({"run": r["run"], "label": r["label"], "replayed_stop": stop_it,
                              "best_heldout_iteration": best_it,
                              "max_3d": max((v for _, v in p3), default=None),
                              "iterations_run": info.get("iterations_run"),
                              "planned": info.get("iterations_planned")})
            else:
                stop = info.get("iterations_run")
                if stop is not None and "budget" not in str(info.get("stopped_by", "")):
                    ax.axvline(stop, color="tab:green", ls="-.", lw=1)
                    ax.annotate("early stop", (stop, ax.get_ylim()[0]), rotation=90,
                                fontsize=7, va="bottom", ha="right", color="tab:green")
                facts.append({"run": r["run"], "label": r["label"],
                              "stopped_at": stop, "stopped_by": info.get("stopped_by"),
                              "best_iteration": info.get("best_iteration"),
                              "kept_iteration": info.get("kept_iteration"),
                              "psnr_3d": r["metrics"].get("psnr_3d"),
                              "planned": info.get("iterations_planned")})
        ax.set_xlabel("iteration")
        ax.set_ylabel("held-out view PSNR (dB)")
        if any3d:
            ax2.set_ylabel("3-D PSNR (dB)", color="tab:red")
        else:
            ax2.set_yticks([])
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="lower right")
        ax.set_title(f"iteration analysis: {case}")
        fig.tight_layout()
        png = img_dir / f"iterations_{case}.png"
        fig.savefig(png, dpi=90)
        plt.close(fig)
        out.append((case, png, facts))
    return out


def heldout_rows(rows) -> list:
    """Table 1's held-out-stopped classical runs, renamed "<run> (held-out)" so that they
    sit beside the speed experiment's fixed-sweep curves of the same method."""
    return [{**r, "run": f"{r['run']} (held-out)"} for r in rows
            if r["run"] in CLASSICAL and _heldout(r)]


def _speed_points(r) -> list:
    """[(seconds, 3-D PSNR)] a run offers: its logged curve and its final result. A
    held-out-stopped run offers its result only (its oracle sweeps are not results)."""
    pts = []
    if not _heldout(r):
        prog = _read_csv(Path(r["dir"]) / "progress_log.csv")
        if prog:
            pts = [(s, p) for s, p in zip(_col(prog, "seconds"), _col(prog, "psnr_3d"))
                   if p is not None and s is not None]
        else:
            log = _read_csv(Path(r["dir"]) / "train_log.csv")
            pts = [(s, p) for s, p in zip(_col(log, "seconds"), _col(log, "psnr_3d"))
                   if p is not None and s is not None]
    t, p = _value(r, "seconds"), _value(r, "psnr_3d")
    return pts + ([(t, p)] if t is not None and p is not None else [])


def anytime_table(rows) -> tuple[list, list]:
    """(header, body): per case and run the best 3-D PSNR among the points it offers
    (``_speed_points``) within each of BUDGETS seconds; "—" = nothing by then."""
    header = ["case", "run"] + [f"best within {b} s" for b in BUDGETS]
    body = []
    for case, _ in _cases(rows):
        for r in rows:
            if r["case"] != case or not r.get("metrics"):
                continue
            pts = _speed_points(r)
            line = [case, r["run"]]
            for b in BUDGETS:
                within = [p for t, p in pts if t <= b]
                line.append(_fmt(max(within), 2) if within else DASH)
            body.append(line)
    return header, body


def plot_speed(rows, img_dir: Path) -> list:
    """Per case: 3-D PSNR against wall-clock seconds for every method (the any-time
    front); returns [(case, png, {run: "curve" | "point"})]. Held-out-stopped runs show
    their result (star) and, hollow, their oracle (labelled; it decides nothing)."""
    plt = _plt()
    out = []
    for case, _ in _cases(rows):
        runs = [r for r in rows if r["case"] == case and r.get("metrics")]
        if not runs:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        kinds = {}
        for i, r in enumerate(runs):
            color = f"C{i % 10}"
            m = r["metrics"]
            pts = _speed_points(r)
            curve = pts[:-1] if m.get("psnr_3d") is not None and pts else pts
            if curve:
                ax.plot(*zip(*curve), "-", color=color, marker=".", ms=4, label=r["run"])
                kinds[r["run"]] = "curve"
            else:
                kinds[r["run"]] = "point"
            t = _value(r, "seconds")
            if m.get("psnr_3d") is not None and t is not None:
                ax.plot([t], [m["psnr_3d"]], "*", ms=11, color=color,
                        label=None if curve else r["run"])
            oracle = (m.get("method_info") or {}).get("oracle") or {}
            if oracle.get("psnr_3d_best") is not None and t is not None:
                ax.plot([t], [oracle["psnr_3d_best"]], "o", ms=8, mfc="none", color=color,
                        label=f"{r['run']} oracle")
        ax.set_xscale("log")
        ax.set_xlabel("wall-clock seconds (log)")
        ax.set_ylabel("3-D PSNR (dB)")
        ax.set_title(f"speed vs error: {case}  (star = result; hollow = oracle)")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        png = img_dir / f"speed_{case}.png"
        fig.savefig(png, dpi=90)
        plt.close(fig)
        out.append((case, png, kinds))
    return out


def views_table_and_plot(rows, img_dir: Path):
    """(header, body, png): mean PSNR per method and view count, and a plot per case."""
    by = {}
    for r in rows:
        method = r.get("method") or r["run"].rsplit("_v", 1)[0]
        v = r.get("views")
        if v is None and "_v" in r["run"]:
            v = int(r["run"].rsplit("_v", 1)[1])
        by.setdefault(method, {}).setdefault(int(v), []).append(r)
    views = sorted({v for d in by.values() for v in d})
    cases = _cases(rows)
    header = ["method"] + [f"{v} views PSNR / SSIM" for v in views]
    body = []
    methods = [m for m in METHOD_ORDER if m in by] + [m for m in by if m not in METHOD_ORDER]
    for m in methods:
        line = [METHOD_NAMES.get(m, m)]
        for v in views:
            sel = {r["case"]: r for r in by[m].get(v, [])}
            ps = _mean_all([_value(sel.get(c), "psnr_3d") for c, _ in cases])
            ss = _mean_all([_value(sel.get(c), "ssim_3d") for c, _ in cases])
            line.append(DASH if ps is None else f"{ps:.2f} / {ss:.3f}")
        body.append(line)
    plt = _plt()
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 3.6), squeeze=False)
    for ax, (case, _) in zip(axes[0], cases):
        for m in methods:
            pts = sorted((v, _value(r, "psnr_3d")) for v, rs in by[m].items() for r in rs
                         if r["case"] == case and _value(r, "psnr_3d") is not None)
            if pts:
                ax.plot(*zip(*pts), "o-", label=m)
        ax.set_title(case)
        ax.set_xlabel("training views")
        ax.set_ylabel("3-D PSNR (dB)")
        ax.set_xticks(views)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    png = img_dir / "views.png"
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return header, body, png


def montage(out_dir: Path, rows, case: str, png: Path) -> Path | None:
    """Central z slice of the ground truth and of every method's result, with |error|."""
    gt_path = Path(out_dir) / "data" / case / "vol_gt.npy"
    if not gt_path.is_file():
        return None
    gt = np.load(gt_path)
    preds = []
    for r in rows:
        if r["case"] == case and r.get("metrics") and (Path(r["dir"]) / "vol_pred.npy").is_file():
            preds.append((r["run"], np.load(Path(r["dir"]) / "vol_pred.npy"),
                          r["metrics"].get("psnr_3d")))
    if not preds:
        return None
    plt = _plt()
    z = gt.shape[2] // 2
    vmax = float(max(gt.max(), 1e-6))
    n = len(preds) + 1
    fig, axes = plt.subplots(2, n, figsize=(2.4 * n + 0.8, 5.0), squeeze=False,
                             constrained_layout=True)
    axes[0][0].imshow(gt[:, :, z], cmap="gray", vmin=0, vmax=vmax)
    axes[0][0].set_title("ground truth", fontsize=9)
    axes[1][0].axis("off")
    for j, (name, vol, p) in enumerate(preds, start=1):
        axes[0][j].imshow(vol[:, :, z], cmap="gray", vmin=0, vmax=vmax)
        axes[0][j].set_title(f"{name}\n{p:.2f} dB" if p is not None else name, fontsize=9)
        im = axes[1][j].imshow(np.abs(vol[:, :, z] - gt[:, :, z]), cmap="magma", vmin=0,
                               vmax=0.25 * vmax)
        axes[1][j].set_title("|error|", fontsize=8)
    for a in axes.ravel():
        a.set_xticks([]), a.set_yticks([])
    fig.colorbar(im, ax=axes[:, -1].tolist(), shrink=0.6,
                 label="|error| (images: 0 to max of ground truth)")
    fig.suptitle(f"{case}: central z slice [x, y] (x down the rows)", fontsize=10)
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png
