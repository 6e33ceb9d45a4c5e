"""The results report: markdown tables and plots from an experiments directory.

    mi-grg report --out results/cpu --report docs/results.md

Reads ``OUT/<experiment>/runs.json`` (written by ``mi_grg.lab.runner``) and each run's
``metrics.json`` / ``train_log.csv`` / ``progress_log.csv``; writes the markdown file and
its PNGs under ``<report dir>/img/results/``. Only numbers found in those files appear in
our tables; a missing or failed run shows as "—". The paper's numbers are transcribed from
its tables and labelled as such (its own data, X-3D at 256^3 / 512^2, not comparable case by
case).
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from mi_grg.lab.finished import ROW_TYPES, read_finished, read_runs

DASH = "—"
CATS = ("HO", "BS", "AO")
METHOD_ORDER = ("fdk", "sart", "asd-pocs", "pdhg", "pdhg-morozov", "sart-fixed",
                "asd-pocs-fixed", "r2", "gr-paper", "gr")
METHOD_NAMES = {"fdk": "FDK", "sart": "SART", "asd-pocs": "ASD-POCS", "pdhg": "PDHG (TV)",
                "pdhg-morozov": "PDHG (TV, weight by Morozov's rule)",
                "sart-fixed": "SART (fixed 10 sweeps)",
                "asd-pocs-fixed": "ASD-POCS (fixed 10 sweeps)",
                "r2": "R2-Gaussian (r2)",
                "gr-paper": "GR-Gaussian, the paper's configuration (gr-paper)",
                "gr": "GR-Gaussian (gr)"}
#: Names in the summary's time line where the first words of METHOD_NAMES are ambiguous.
SHORT_NAMES = {"pdhg-morozov": "PDHG (Morozov)", "gr-paper": "GR-Gaussian (paper)"}
#: Classical methods (every row of theirs competes with gr in the summary's margin).
CLASSICAL = ("fdk", "sart", "asd-pocs", "pdhg", "pdhg-morozov", "sart-fixed",
             "asd-pocs-fixed")
#: Time budgets of the any-time table (seconds).
BUDGETS = (1, 10, 60, 300)

# GR-Gaussian paper, Table 1 (25 views; X-3D data set HO/BS/AO/Average, RD = real-world
# data set), PSNR (dB) / SSIM, transcribed from the .tex.
PAPER_TABLE1 = {
    "FDK": [(22.64, 0.319), (23.45, 0.296), (22.95, 0.336), (23.01, 0.317), (23.30, 0.335)],
    "SART": [(29.58, 0.773), (32.37, 0.878), (31.48, 0.825), (31.14, 0.825), (31.52, 0.790)],
    "ASD-POCS": [(29.42, 0.810), (31.40, 0.887), (30.58, 0.845), (30.47, 0.847),
                 (31.32, 0.810)],
    "NAF": [(32.05, 0.841), (34.36, 0.930), (35.34, 0.909), (33.92, 0.893), (32.92, 0.772)],
    "SAX-NeRF": [(32.53, 0.858), (34.67, 0.940), (35.85, 0.917), (34.35, 0.905),
                 (33.49, 0.793)],
    "R2-GS": [(32.98, 0.881), (35.08, 0.944), (37.52, 0.945), (35.19, 0.922), (35.03, 0.837)],
    "Ours (GR-Gaussian)": [(33.47, 0.891), (35.56, 0.952), (38.55, 0.955), (35.86, 0.933),
                           (35.95, 0.858)],
}
# Table 2 (ablation; X-3D and real-world PSNR / SSIM).
PAPER_TABLE2 = [("Baseline (R2-GS)", 35.20, 0.923, 35.28, 0.836),
                ("+ De-Init", 35.61, 0.931, 35.90, 0.857),
                ("+ PGA", 35.77, 0.932, 35.62, 0.848),
                ("+ De-Init + PGA", 35.86, 0.932, 35.95, 0.858)]
# Table 3 (X-3D rows): k = 4..8 and sigma_d = 1..5.
PAPER_TABLE3_K = {"PSNR": (35.80, 35.84, 35.86, 35.87, 35.89),
                  "SSIM": (0.932, 0.932, 0.933, 0.933, 0.934),
                  "Time (s)": (536, 567, 629, 763, 865)}
PAPER_TABLE3_SIGMA = {"PSNR": (35.60, 35.72, 35.86, 35.68, 35.43),
                      "SSIM": (0.926, 0.928, 0.933, 0.927, 0.925)}


# ---------------------------------------------------------------------------- loading
def _read_json(path: Path):
    from mi_grg.data.inputs import read_json
    try:
        return read_json(path)
    except (OSError, ValueError):
        return None


def _dict(value) -> dict:
    return value if isinstance(value, dict) else {}


def load_runs(out_dir) -> dict:
    """{experiment: [row]} where row has case, run, category, label, method, views, dir,
    status and ``metrics`` (the run's metrics.json, or None when missing)."""
    out = Path(out_dir)
    result = {}
    for exp_dir in sorted(p for p in out.iterdir() if p.is_dir() and p.name != "data"):
        index = read_runs(exp_dir / "runs.json")
        rows = [] if index is None else index["runs"]
        if index is None:   # no runs.json: scan the layout
            for m in sorted(exp_dir.glob("*/*/metrics.json")):
                met = _dict(_read_json(m))
                sc = _dict(_dict(met.get("data")).get("suite_case"))
                row = {"case": m.parent.parent.name, "run": m.parent.name,
                       "category": sc.get("category"), "label": m.parent.name,
                       "method": met.get("method"), "views": sc.get("views")}
                rows.append({k: v if isinstance(v, ROW_TYPES[k]) else None
                             for k, v in row.items()})
        for r in rows:
            d = exp_dir / r["case"] / r["run"]
            r["dir"] = str(d)
            r["metrics"] = read_finished(d, r)   # None unless the run reads back
        if rows:
            result[exp_dir.name] = rows
    return result


def _commands(out_dir) -> list:
    cmds = []
    for f in sorted(Path(out_dir).glob("*/runs.json")):
        cmds += read_runs(f)["commands"]
    return cmds


def _value(row, key):
    m = row.get("metrics") if row else None
    if not m or key not in m or m[key] is None:
        return None
    v = m[key]
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def _fmt(v, digits):
    return DASH if v is None else f"{v:.{digits}f}"


def _fmt_time(v):
    if v is None:
        return DASH
    if v < 0.1:
        return f"{v:.3f}"
    return f"{v:.2f}" if v < 10 else f"{v:.0f}" if v >= 1000 else f"{v:.1f}"


def _mean_all(values):
    """Mean only when every value is present (never averages over a partial set)."""
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(values))


def _cases(rows) -> list:
    seen = []
    for r in rows:
        if r["case"] not in [c for c, _ in seen]:
            seen.append((r["case"], r.get("category")))
    return seen


def _index(rows) -> dict:
    return {(r["case"], r["run"]): r for r in rows}


def _methods_present(rows, order=METHOD_ORDER) -> list:
    runs = []
    for r in rows:
        if r["run"] not in runs:
            runs.append(r["run"])
    known = [m for m in order if m in runs]
    return known + [m for m in runs if m not in known]


# ---------------------------------------------------------------------------- tables
def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def complete_cases(rows) -> list:
    """[(case, category)] of the cases where every method that has any result has one:
    means are taken over these only, so that no method's mean covers other cases."""
    idx = _index(rows)
    runs = [m for m in _methods_present(rows)
            if any(_value(r, "psnr_3d") is not None for r in rows if r["run"] == m)]
    return [(c, cat) for c, cat in _cases(rows)
            if all(_value(idx.get((c, m)), "psnr_3d") is not None for m in runs)]


def table1_rows(rows, cases=None) -> tuple[list, list]:
    """(header, body) of our Table 1: per method the per-category and overall mean PSNR /
    SSIM and the mean time (s); a mean is shown only when every case in it has a result."""
    idx = _index(rows)
    cases = _cases(rows) if cases is None else cases
    header = ["method"]
    cats = [c for c in CATS if any(cat == c for _, cat in cases)]
    for c in cats:
        n = sum(cat == c for _, cat in cases)
        header += [f"{c} PSNR ({n})", f"{c} SSIM"]
    header += [f"Average PSNR ({len(cases)})", "Average SSIM", "time (s)"]
    body = []
    # every method of the paper's comparison, present or not ("—" rows say what is missing)
    runs = list(METHOD_ORDER) + [m for m in _methods_present(rows) if m not in METHOD_ORDER]
    for m in runs:
        line = [METHOD_NAMES.get(m, m)]
        for c in cats:
            sel = [idx.get((case, m)) for case, cat in cases if cat == c]
            line += [_fmt(_mean_all([_value(r, "psnr_3d") for r in sel]), 2),
                     _fmt(_mean_all([_value(r, "ssim_3d") for r in sel]), 3)]
        sel = [idx.get((case, m)) for case, _ in cases]
        line += [_fmt(_mean_all([_value(r, "psnr_3d") for r in sel]), 2),
                 _fmt(_mean_all([_value(r, "ssim_3d") for r in sel]), 3),
                 _fmt_time(_mean_all([_value(r, "seconds") for r in sel]))]
        body.append(line)
    return header, body


def oracle_rows(rows) -> tuple[list, list]:
    """(header, body): each held-out-stopped classical run, what it chose and its oracle
    (the best 3-D PSNR over the chosen setting's sweeps, chosen with the ground truth;
    reported only, it decided nothing)."""
    header = ["case", "run", "3-D PSNR", "chosen (held-out views)", "oracle 3-D PSNR (sweep)",
              "oracle − result (dB)"]
    body = []
    for r in rows:
        if r["run"] not in CLASSICAL or not _heldout(r):
            continue
        info = r["metrics"]["method_info"]
        ch = info.get("chosen") or {}
        setting = ", ".join(f"{k}={v:g}" for k, v in (ch.get("setting") or {}).items())
        chosen = (setting + ", " if setting else "") + f"{ch.get('sweeps')} sweeps"
        o = info.get("oracle") or {}
        best = o.get("psnr_3d_best")
        body.append([r["case"], r["run"], _fmt(_value(r, "psnr_3d"), 2), chosen,
                     f"{_fmt(best, 2)} ({o.get('best_sweep')})" if best is not None else DASH,
                     _fmt(o.get("gap_db"), 2)])
    return header, body


def classical_margin(rows) -> dict:
    """gr − the best classical row per case, against the held-out-stopped rows (FDK and
    the iterative methods that stopped on held-out views) and against the fixed-sweep
    rows (the paper's protocol; runs made before held-out stopping count as fixed):
    {"heldout": [(case, run, margin)], "fixed": [...]}."""
    idx = _index(rows)
    out = {"heldout": [], "fixed": []}
    for c, _ in _cases(rows):
        g = _value(idx.get((c, "gr")), "psnr_3d")
        if g is None:
            continue
        for kind in out:
            pool = {}
            for m in CLASSICAL:
                r = idx.get((c, m))
                p = _value(r, "psnr_3d")
                if p is None:
                    continue
                if m == "fdk" or (kind == "heldout") == _heldout(r):
                    pool[m] = p
            if any(m != "fdk" for m in pool):
                best = max(pool, key=pool.get)
                out[kind].append((c, best, g - pool[best]))
    return out


def per_case_rows(rows) -> tuple[list, list]:
    """(header, body): one line per case, PSNR / SSIM / seconds of every run."""
    idx = _index(rows)
    runs = _methods_present(rows)
    header = ["case", "cat."] + [f"{r}" for r in runs]
    body = []
    for case, cat in _cases(rows):
        line = [case, cat or DASH]
        for run in runs:
            r = idx.get((case, run))
            p, s, t = (_value(r, "psnr_3d"), _value(r, "ssim_3d"), _value(r, "seconds"))
            line.append(DASH if p is None else f"{p:.2f} / {s:.3f} / {_fmt_time(t)} s")
        body.append(line)
    return header, body


def paper_table1_md() -> str:
    header = ["method (paper)", "HO PSNR", "HO SSIM", "BS PSNR", "BS SSIM", "AO PSNR",
              "AO SSIM", "Average PSNR", "Average SSIM", "RD PSNR", "RD SSIM"]
    body = [[name] + [f"{v:.2f}" if i % 2 == 0 else f"{v:.3f}"
                      for pair in vals for i, v in enumerate(pair)]
            for name, vals in PAPER_TABLE1.items()]
    return _md_table(header, body)


def _paper_fmt(metric: str, v) -> str:
    return f"{v:.2f}" if metric == "PSNR" else f"{v:.3f}" if metric == "SSIM" else f"{v}"


def _runs_summary(rows, runs, labels=None) -> tuple[list, list]:
    """Mean PSNR / SSIM / time per run name over the cases of ``rows`` (complete only)."""
    idx = _index(rows)
    cases = _cases(rows)
    header = ["run", f"PSNR ({len(cases)} cases)", "SSIM", "time (s)"] + \
        [f"{c} PSNR" for c, _ in cases]
    body = []
    for run in runs:
        sel = [idx.get((c, run)) for c, _ in cases]
        if all(r is None for r in sel):
            continue
        label = (labels or {}).get(run) or next((r.get("label") for r in sel if r), run)
        body.append([label, _fmt(_mean_all([_value(r, "psnr_3d") for r in sel]), 2),
                     _fmt(_mean_all([_value(r, "ssim_3d") for r in sel]), 3),
                     _fmt_time(_mean_all([_value(r, "seconds") for r in sel]))] +
                    [_fmt(_value(r, "psnr_3d"), 2) for r in sel])
    return header, body


def _sweep_table(rows, prefix, values, with_time=True) -> tuple[list, list]:
    idx = _index(rows)
    cases = _cases(rows)
    runs = [f"{prefix}{v:g}" for v in values]
    header = ["metric"] + [f"{prefix.rstrip('_')}={v:g}" for v in values]
    body = []
    metrics = [("PSNR", "psnr_3d", 2), ("SSIM", "ssim_3d", 3)]
    if with_time:
        metrics.append(("time (s)", "seconds", None))
    for name, key, dig in metrics:
        line = [f"{name} (mean of {len(cases)})"]
        for run in runs:
            v = _mean_all([_value(idx.get((c, run)), key) for c, _ in cases])
            line.append(_fmt_time(v) if dig is None else _fmt(v, dig))
        body.append(line)
    return header, body


#: Metrics of the seeds table: key -> (label, decimals, unit).
SEED_METRICS = {"psnr_3d": ("PSNR", 2, "dB"), "ssim_3d": ("SSIM", 4, "")}


def seeds_table(rows, key: str = "psnr_3d") -> tuple[list, list, dict]:
    """Per case: r2 and gr 3-D PSNR (or SSIM: ``key="ssim_3d"``) over training seeds (mean
    +- sample sd) and the paired difference gr - r2 (same seed, same data); a last row pools
    every pair.

    Returns (header, body, pooled) with pooled = {"n", "mean", "sd", "se"} of all paired
    differences (se = sd / sqrt(n); empty without pairs)."""
    if key not in SEED_METRICS:
        raise ValueError(f"seeds_table: key must be one of {sorted(SEED_METRICS)}, got {key!r}")
    name, dig, _ = SEED_METRICS[key]
    by = {}
    for r in rows:
        m, _, sd = r["run"].rpartition("_s")
        v = _value(r, key)
        if m in ("r2", "gr") and sd.isdigit() and v is not None:
            by.setdefault(r["case"], {}).setdefault(int(sd), {})[m] = v

    def ms(vals, sign=""):
        if not vals:
            return DASH
        sd = f" ± {np.std(vals, ddof=1):.{dig}f}" if len(vals) > 1 else ""
        return f"{np.mean(vals):{sign}.{dig}f}{sd}"

    def span(d):
        return f"{min(d):+.{dig}f} .. {max(d):+.{dig}f}" if d else DASH

    header = ["case", "seeds", f"r2 {name}", f"gr {name}", "gr − r2 (paired)",
              "range of gr − r2", "gr ahead"]
    body, pooled_d = [], []
    for case, _ in _cases(rows):
        seeds = by.get(case, {})
        d = [x["gr"] - x["r2"] for x in seeds.values() if "gr" in x and "r2" in x]
        pooled_d += d
        body.append([case, str(len(seeds)), ms([x["r2"] for x in seeds.values() if "r2" in x]),
                     ms([x["gr"] for x in seeds.values() if "gr" in x]),
                     ms(d, "+"), span(d), f"{sum(x > 0 for x in d)} of {len(d)}"])
    pooled = {}
    if pooled_d:
        n = len(pooled_d)
        sd = float(np.std(pooled_d, ddof=1)) if n > 1 else float("nan")
        pooled = {"n": n, "mean": float(np.mean(pooled_d)), "sd": sd,
                  "se": sd / math.sqrt(n) if n > 1 else float("nan")}
        body.append([f"all ({n} pairs)", "", "", "", ms(pooled_d, "+"), span(pooled_d),
                     f"{sum(x > 0 for x in pooled_d)} of {n}"])
    return header, body, pooled


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


def replay_early_stop(iterations, heldout, drop=None, patience=None, start=0, noise=None):
    """(iteration at which ``EarlyStopper(drop, patience, noise)`` would stop on the logged
    held-out PSNR or None, the best iteration); ``drop``, ``patience`` and ``noise`` default
    to TrainConfig's stop_drop, stop_patience and stop_noise. Like training, only evaluations
    at iterations >= ``start`` (the end of densification) are judged; the earlier ones inform
    the noise margin."""
    from mi_grg.training.config import TrainConfig
    from mi_grg.protocol.early_stop import EarlyStopper
    cfg = TrainConfig()
    st = EarlyStopper(drop=cfg.protocol.stop_drop if drop is None else drop,
                      patience=cfg.protocol.stop_patience if patience is None else patience,
                      noise=cfg.protocol.stop_noise if noise is None else noise)
    for it, v in zip(iterations, heldout):
        if v is None:
            continue
        if it < start:
            st.observe(int(it), v)
        elif st.update(int(it), v) == "stop":
            return int(it), st.best_iteration
    return None, st.best_iteration


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
                stop_it, best_it = replay_early_stop(it, ho, start=start)
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


def _heldout(row) -> bool:
    """Whether a run chose its sweeps (and regularisation) on held-out views."""
    m = (row or {}).get("metrics") or {}
    return (m.get("method_info") or {}).get("protocol") == "heldout"


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


# ---------------------------------------------------------------------------- summary
def summary_lines(out_dir) -> list:
    """Three lines for the README: where gr wins, where not, at what time cost (Table 1)."""
    rows = load_runs(out_dir).get("table1", [])
    idx = _index(rows)
    cases = [c for c, _ in _cases(rows)]
    wins, losses, vs_r2 = [], [], []
    for c in cases:
        g = _value(idx.get((c, "gr")), "psnr_3d")
        others = {m: _value(idx.get((c, m)), "psnr_3d") for m in METHOD_ORDER
                  if m != "gr" and not m.endswith("-fixed")}
        others = {m: v for m, v in others.items() if v is not None}
        if g is None or not others:
            continue
        best_m = max(others, key=others.get)
        (wins if g > others[best_m] else losses).append((c, best_m, g - others[best_m]))
        if others.get("r2") is not None:
            vs_r2.append(g - others["r2"])
    if not wins and not losses:
        return ["No Table 1 runs with both gr and another method yet: no summary."]
    line1 = (f"GR-Gaussian (gr) has the best 3-D PSNR on {len(wins)} of "
             f"{len(wins) + len(losses)} cases"
             + (f" ({', '.join(f'{c} +{d:.2f} dB' for c, _, d in wins)})" if wins else "")
             + (f"; against R2-Gaussian it is {np.mean(vs_r2):+.2f} dB on average "
                f"(better on {sum(d > 0 for d in vs_r2)} of {len(vs_r2)})" if vs_r2 else "")
             + ".")
    line2 = ("It is not the best on: " + ", ".join(
        f"{c} ({METHOD_NAMES.get(m, m)} ahead by {-d:.2f} dB)" for c, m, d in losses) + "."
        if losses else "It is the best on every case of Table 1.")
    done = [c for c, _ in complete_cases(rows)]
    times = {m: _mean_all([_value(idx.get((c, m)), "seconds") for c in done])
             for m in METHOD_ORDER}
    parts = [f"{SHORT_NAMES.get(m) or METHOD_NAMES[m].split(' (')[0]}"
             f"{' (fixed)' if m.endswith('-fixed') else ''} "
             f"{_fmt_time(t)} s" for m, t in times.items() if t is not None]
    ratio = ""
    if times.get("gr") and times.get("r2"):
        ratio = f" (gr / r2 = {times['gr'] / times['r2']:.2f}x)"
    over = "" if len(done) == len(cases) else f" (over the {len(done)} complete cases)"
    line3 = f"Mean time per case{over}: " + ", ".join(parts) + ratio + "."
    return [line1, line2, line3, margin_line(rows)]


def margin_line(rows) -> str:
    """The headline margin of gr over the best classical method, on the fair rows."""
    mg = classical_margin(rows)
    fair, fixed = mg["heldout"], mg["fixed"]
    if not fair:
        line = ("No held-out-stopped classical runs in these results (SART / ASD-POCS ran a "
                "fixed sweep count): re-run Table 1's sart, asd-pocs and pdhg rows for the "
                "fair margin")
    else:
        line = (f"gr − the best classical method stopped and tuned on held-out views "
                f"(without the ground truth, as gr is): {np.mean([d for _, _, d in fair]):+.2f} dB on average over "
                f"{len(fair)} case(s) (" + ", ".join(f"{c} {d:+.2f} vs {m}"
                                                     for c, m, d in fair) + ")")
    if fixed:
        line += (f"; against the fixed-sweep rows the paper's tables used: "
                 f"{np.mean([d for _, _, d in fixed]):+.2f} dB")
    return line + "."


# ---------------------------------------------------------------------------- report
def _setup_md(all_rows: dict) -> str:
    machines, sizes, iters, sart = set(), set(), {}, set()
    seen = set()
    for exp, rows in all_rows.items():
        for r in rows:
            m = r.get("metrics")
            real = os.path.realpath(r["dir"])   # a linked run counts once
            if not m or real in seen:
                continue
            seen.add(real)
            mc = m.get("machine", {})
            machines.add((mc.get("variant"), mc.get("cpu"), mc.get("cores"),
                          mc.get("mitsuba"), mc.get("drjit"), mc.get("mi_grg")))
            d = m.get("data") or {}
            sizes.add((tuple(d.get("n_voxel") or m.get("nVoxel") or ()),
                       tuple(d.get("n_detector") or ()), d.get("mode"),
                       m.get("n_train_views")))
            info = m.get("method_info") or {}
            if "iterations_run" in info:
                iters.setdefault(m["method"], []).append(
                    (info["iterations_run"], info.get("iterations_planned")))
            if m.get("method") in ("sart", "asd-pocs", "pdhg", "sart-curve", "asd-pocs-curve",
                                   "pdhg-curve"):
                o = m.get("options") or {}
                stop = "held-out" if info.get("protocol") == "heldout" else "fixed"
                sart.add((m["method"], f"{o.get('n_iter', 'default')} ({stop})"))
    lines = ["Machine(s) and variant(s) the runs used (from metrics.json):", ""]
    for v, cpu, cores, mi_v, dr_v, code in sorted(machines, key=str):
        lines.append(f"- variant `{v}`, CPU {cpu}, {cores} cores, Mitsuba {mi_v}, "
                     f"Dr.Jit {dr_v}, mi_grg {code or 'not recorded'}")
    lines += ["", "Sizes (volume [x, y, z], detector [v, u], beam, training views):", ""]
    for nv, nd, mode, views in sorted(sizes, key=str):
        lines.append(f"- {'x'.join(map(str, nv))} volume, {'x'.join(map(str, nd))} detector, "
                     f"{mode}, {views} views")
    if iters:
        lines += ["", "Training iterations (run / planned; early stopping on held-out "
                      "views ends runs before the plan):", ""]
        for m, its in sorted(iters.items()):
            run = [a for a, _ in its]
            planned = sorted({b for _, b in its if b is not None})
            lines.append(f"- {m}: {len(its)} runs, {min(run)}-{max(run)} iterations run "
                         f"(median {int(np.median(run))}), planned {planned}")
    from mi_grg.lab.staleness import stale_keys
    older = {}
    for exp, rows in all_rows.items():
        for r in rows:
            keys = stale_keys(r["metrics"]) if r.get("metrics") else []
            if keys:
                older.setdefault(exp, [0, set()])[0] += 1
                older[exp][1].update(keys)
    if older:
        lines += ["", "Runs made under other defaults than this code's (their numbers stand as "
                      "they ran; `bash experiments/run_cpu.sh` re-runs them):", ""]
        for exp, (n, keys) in sorted(older.items()):
            lines.append(f"- {exp}: {n} run(s), differing in {', '.join(sorted(keys))}")
    if sart:
        lines += ["", "Iterative baselines: " + ", ".join(
            f"{m} n_iter={n}" for m, n in sorted(sart, key=str)) +
            " (\"default\" = the method's default, see mi_grg.classical.iterative)."]
    return "\n".join(lines)


def _absent(name: str, out: Path) -> str:
    """The line for an experiment with no runs in ``out``: how to add it."""
    return (f"{DASH} (no {name} runs in `{out}`; add them with `mi-grg experiment {name} "
            f"--suite SUITE --out {out}`, e.g. SUITE = experiments/suite_cpu_full.json, "
            "then regenerate this report)")


def _intro_md(out: Path, report: Path, all_rows: dict) -> list:
    """The report's head: how to regenerate it, what the numbers mean, summary, setup."""
    md = ["# Results", "",
          f"Generated by `mi-grg report --out {out} --report {report}` from the runs in "
          f"`{out}`. Regenerate everything with:", "", "```"]
    md += _commands(out) + [f"mi-grg report --out {out} --report {report}", "```", ""]
    md += ["Our numbers: 3-D PSNR (dB) and SSIM of the reconstructed volume against the "
           "simulated ground truth, R2-Gaussian's convention (data range 1, SSIM over 2-D "
           "slices), mean over cases; time = wall-clock seconds of the whole reconstruction. "
           f"\"{DASH}\" = no result (run missing or failed); a mean needs every case.", ""]
    md += ["## Summary", ""] + [f"{i + 1}. {s}" for i, s in enumerate(summary_lines(out))]
    md += ["", "## Setup", "", _setup_md(all_rows), ""]
    return md


def _table1_md(t1, out: Path) -> list:
    """Table 1 (methods x cases), its per-case and oracle tables, the paper's Table 1."""
    md = ["## Table 1: methods x cases", ""]
    if t1:
        h, b = table1_rows(t1)
        md += ["Ours (category in parentheses: number of cases):", "", _md_table(h, b), ""]
        done = complete_cases(t1)
        if 0 < len(done) < len(_cases(t1)):
            h, b = table1_rows(t1, done)
            md += [f"Only {len(done)} of the {len(_cases(t1))} cases have a result from every "
                   "method, so some means above are missing. The same table over those "
                   f"{len(done)} cases ({', '.join(c for c, _ in done)}):", "",
                   _md_table(h, b), ""]
        h, b = per_case_rows(t1)
        md += ["Per case (PSNR / SSIM / time):", "", _md_table(h, b), ""]
        h, b = oracle_rows(t1)
        if b:
            md += ["SART, ASD-POCS and PDHG rows choose their sweeps (and ASD-POCS's TV "
                   "weight alpha, PDHG's lam) without the ground truth on the training views "
                   "with one in 8 held out, then run the choice on all views "
                   "(mi_grg.protocol.heldout): PDHG by gr's rule on the held-out PSNR, SART "
                   "and ASD-POCS by the discrepancy principle (the first sweep whose fitted-"
                   "view residual reaches the noise level measured on the held-out views), "
                   "the TV weights by the one-standard-error rule on the held-out PSNR over "
                   "a log grid widened until the choice is interior (pdhg-morozov: PDHG's "
                   "weight by Morozov's discrepancy principle, the rule of gr's "
                   "refinement); the \"fixed\" rows run "
                   "10 sweeps at TIGRE's defaults, as the paper's tables. Beside each "
                   "held-out result, the **oracle**: the best 3-D PSNR over the chosen "
                   "setting's sweeps, picked with the ground truth; it is reported only and "
                   "decided nothing.", "", _md_table(h, b), ""]
    else:
        md += [_absent("table1", out), ""]
    md += ["**The paper's Table 1** (GR-Gaussian paper, 25 views, on its own data: X-3D at "
           "256^3 volumes / 512^2 projections, RD = real-world scans; NAF and SAX-NeRF are not "
           "implemented here). Transcribed for reference: NOT comparable case by case with "
           "ours (different objects, sizes and noise):", "", paper_table1_md(), ""]
    return md


def _table2_md(t2, out: Path) -> list:
    """Table 2 (ablation) and the paper's."""
    md = ["## Table 2: ablation", ""]
    if t2:
        from mi_grg.lab.plan import table2_variants
        h, b = _runs_summary(t2, [run for run, *_ in table2_variants()])
        md += [_md_table(h, b), ""]
    else:
        md += [_absent("table2", out), ""]
    md += ["The paper's Table 2 (X-3D / real-world PSNR, SSIM; its own data, for reference):",
           "", _md_table(["paper", "X-3D PSNR", "X-3D SSIM", "RD PSNR", "RD SSIM"],
                         [[n, f"{a:.2f}", f"{b:.3f}", f"{c:.2f}", f"{d:.3f}"]
                          for n, a, b, c, d in PAPER_TABLE2]), ""]
    return md


def _table3_md(t3, out: Path) -> list:
    """Table 3 (k and sigma_d sweeps) and the paper's."""
    md = ["## Table 3: k and sigma_d", ""]
    if t3:
        ks = sorted({int(r["run"][1:]) for r in t3 if r["run"][:1] == "k"})
        sds = sorted({float(r["run"][len("sigma_d"):]) for r in t3
                      if r["run"].startswith("sigma_d")})
        if ks:
            md += [_md_table(*_sweep_table(t3, "k", ks)), ""]
        if sds:
            md += [_md_table(*_sweep_table(t3, "sigma_d", sds)), ""]
    else:
        md += [_absent("table3", out), ""]
    md += ["The paper's Table 3 (X-3D rows, its own data and GPU):", "",
           _md_table(["paper"] + [f"k={k}" for k in range(4, 9)],
                     [[n] + [_paper_fmt(n, v) for v in vals]
                      for n, vals in PAPER_TABLE3_K.items()]),
           "", _md_table(["paper"] + [f"sigma_d={s}" for s in range(1, 6)],
                         [[n] + [_paper_fmt(n, v) for v in vals]
                          for n, vals in PAPER_TABLE3_SIGMA.items()]), ""]
    return md


def _iterations_md(it, out: Path, img_dir: Path, rel: str) -> list:
    """Iteration analysis: held-out and 3-D PSNR against iteration, one plot per case."""
    md = ["## Iteration analysis", ""]
    if it:
        from mi_grg.training.config import TrainConfig
        tc = TrainConfig()
        md += ["Held-out-view PSNR (the early-stopping signal, no ground truth) and 3-D PSNR "
               "(when logged) against iteration. Solid: the run with early stopping disabled "
               "(stop_drop 0.99) over the full schedule, with the iteration where the default "
               f"rule (stop when held-out PSNR is more than {100 * tc.protocol.stop_drop:g} % and "
               f"{tc.protocol.stop_noise:g} x its scatter between evaluations below "
               f"its best at {tc.protocol.stop_patience} evaluation(s) in a row, judged once "
               "densification has ended) would have stopped it (dotted, replayed from its "
               "log); dashed: the normal run, its actual stop dash-dotted.", ""]
        for case, png, facts in plot_iterations(it, img_dir):
            md += [f"![iterations {case}]({rel}/{png.name})", ""]
            for f in facts:
                md.append("- " + ", ".join(f"{k}: {v}" for k, v in f.items() if v is not None))
            md.append("")
    else:
        md += [_absent("iterations", out), ""]
    return md


def _speed_md(sp, t1, out: Path, img_dir: Path, rel: str) -> list:
    """Speed against error: plots per case and the best PSNR within a time budget."""
    md = ["## Speed against error", ""]
    if sp:
        speed_cases = {c for c, _ in _cases(sp)}
        sp = sp + [r for r in heldout_rows(t1 or []) if r["case"] in speed_cases]
        md += ["3-D PSNR against wall-clock seconds, one plot per case. Curves: SART / "
               "ASD-POCS / PDHG at a fixed setting after every sweep (progress_log.csv, the time spent scoring "
               "excluded) and r2 / gr from train_log.csv where it holds 3-D PSNR (training-"
               "loop seconds: FDK initialisation and final voxelisation not included); a star "
               "is each run's final result at its total time; a method with only a star "
               "logs no intermediate 3-D PSNR.", ""]
        md[-2] += (" \"(held-out)\" runs are Table 1's held-out-stopped classical runs: "
                   "their star is the result at its time (decision included), the hollow "
                   "circle their oracle (ground-truth-chosen sweep, not a result).")
        for case, png, kinds in plot_speed(sp, img_dir):
            md += [f"![speed {case}]({rel}/{png.name})", "",
                   "- " + ", ".join(f"{k}: {v}" for k, v in kinds.items()), ""]
        h, b = anytime_table(sp)
        md += ["Best 3-D PSNR (dB) reached within a time budget: the best point of a run's "
               "curve or its final result at or before that many seconds (a curve's best "
               "point is picked with the ground truth, as on the plots; a held-out-stopped "
               "run offers its result only):", "", _md_table(h, b), ""]
    else:
        md += [_absent("speed", out), ""]
    return md


def _views_md(vw, out: Path, img_dir: Path, rel: str) -> list:
    """Number of views: table and plot."""
    md = ["## Number of views", ""]
    if vw:
        h, b, png = views_table_and_plot(vw, img_dir)
        md += ["Mean over the cases of the views experiment:", "", _md_table(h, b), "",
               f"![views]({rel}/{png.name})", ""]
    else:
        md += [_absent("views", out), ""]
    return md


def _seeds_md(sd, out: Path) -> list:
    """Training seeds: r2 and gr over seeds, paired differences."""
    md = ["## Training seeds", ""]
    if sd:
        md += ["3-D PSNR (dB) and SSIM of r2 and gr with different training seeds on the same "
               "data (the seed draws the initial points, the view order, the TV blocks and the "
               "split positions; the noise in the data is fixed). Mean ± sample standard "
               "deviation over seeds; \"paired\" = gr − r2 at the same seed.", ""]
        for key, (name, dig, unit) in SEED_METRICS.items():
            h, b, pooled = seeds_table(sd, key)
            md += [f"{name}:", "", _md_table(h, b), ""]
            if pooled.get("n", 0) > 1:
                verdict = ("exceeds" if abs(pooled["mean"]) > 2 * pooled["se"]
                           else "does not exceed")
                u = f" {unit}" if unit else ""
                md += [f"Pooled over the {pooled['n']} pairs: gr − r2 = "
                       f"{pooled['mean']:+.{dig}f}{u} {name}, standard error "
                       f"{pooled['se']:.{dig}f}{u}; the mean {verdict} twice its standard "
                       "error. Pooling treats pairs from different cases as interchangeable; "
                       "where the per-case differences disagree, read the rows.", ""]
    else:
        md += [_absent("seeds", out), ""]
    return md


def _extremes_md(t1, out: Path, img_dir: Path, rel: str) -> list:
    """Montages of the best and worst case by gr's 3-D PSNR."""
    md = ["## Best and worst cases", ""]
    if t1:
        idx = _index(t1)
        ranked = []
        for c, _ in _cases(t1):
            p = _value(idx.get((c, "gr")), "psnr_3d")
            if p is None:
                vals = [_value(r, "psnr_3d") for r in t1 if r["case"] == c]
                vals = [v for v in vals if v is not None]
                p = max(vals) if vals else None
            if p is not None:
                ranked.append((p, c))
        ranked.sort()
        picks = []
        if ranked:
            picks = [("best", ranked[-1][1])] + ([("worst", ranked[0][1])]
                                                 if len(ranked) > 1 else [])
        for which, case in picks:
            png = montage(out, t1, case, img_dir / f"montage_{which}_{case}.png")
            if png is not None:
                md += [f"{which.capitalize()} case by gr's 3-D PSNR (or the best method's "
                       f"where gr is missing): **{case}**", "",
                       f"![{which} {case}]({rel}/{png.name})", ""]
        md += ["Every run also has its own `slices.png` (three central slices, ground truth, "
               "|error|) in its directory under " f"`{out}`.", ""]
    else:
        md += [f"{DASH}", ""]
    return md


def write_report(out_dir, report_path="docs/results.md") -> Path:
    """Write the markdown report (and its PNGs under <report dir>/img/results/), built
    beside them and swapped in whole; never over what the runner wrote
    (``mi_grg.lab.finished.report_target``)."""
    from mi_grg.data.outputs import staged_report
    from mi_grg.lab.finished import report_target
    out, report = Path(out_dir), Path(report_path)
    all_rows = load_runs(out) if out.is_dir() else {}
    img_dir = report_target(out, report, all_rows)
    rel = os.path.relpath(img_dir, report.parent)
    with staged_report(report, img_dir) as (tmp_report, tmp_img):
        _write_md(out, report, all_rows, tmp_report, tmp_img, rel)
    return report


def _write_md(out: Path, report: Path, all_rows: dict, path: Path, img_dir: Path,
              rel: str) -> None:
    """The report of ``all_rows`` into ``path``, its PNGs into ``img_dir``."""
    from mi_grg.lab.compare import comparison_section
    from mi_grg.lab.finished import broken_md
    t1 = all_rows.get("table1")
    md = _intro_md(out, report, all_rows)
    md += _table1_md(t1, out)
    md += _table2_md(all_rows.get("table2"), out)
    md += _table3_md(all_rows.get("table3"), out)
    md += _iterations_md(all_rows.get("iterations"), out, img_dir, rel)
    md += _speed_md(all_rows.get("speed"), t1, out, img_dir, rel)
    md += _views_md(all_rows.get("views"), out, img_dir, rel)
    md += _seeds_md(all_rows.get("seeds"), out)
    md += comparison_section(out, t1, img_dir, rel)
    md += _extremes_md(t1, out, img_dir, rel)
    md += broken_md(all_rows)
    path.write_text("\n".join(md) + "\n")
