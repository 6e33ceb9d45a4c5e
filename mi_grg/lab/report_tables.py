"""The results report's tables: the runs of an experiments directory, loaded
(``load_runs``), and the rows of each table (Table 1 and its oracle / per-case variants,
the sweeps, the seeds); the paper's own tables, transcribed from its .tex and labelled as
such. Figures: ``report_figures``; the markdown file: ``report``."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mi_grg.lab.finished import ROW_TYPES, read_finished, read_runs

DASH = "—"
CATS = ("HO", "BS", "AO")
METHOD_ORDER = ("fdk", "sart", "asd-pocs", "asd-pocs-best", "pdhg", "pdhg-best",
                "pdhg-morozov", "pdhg-cold", "sart-fixed", "asd-pocs-fixed", "r2", "gr-paper",
                "gr-gaussians", "gr")
METHOD_NAMES = {"fdk": "FDK", "sart": "SART", "asd-pocs": "ASD-POCS",
                "asd-pocs-best": "ASD-POCS (TV weight by the best held-out PSNR)",
                "pdhg": "PDHG (TV)",
                "pdhg-best": "PDHG (TV, weight by the best held-out PSNR)",
                "pdhg-morozov": "PDHG (TV, weight by Morozov's rule)",
                "pdhg-cold": "PDHG from zero at gr's refinement weight, to convergence",
                "sart-fixed": "SART (fixed 10 sweeps)",
                "asd-pocs-fixed": "ASD-POCS (fixed 10 sweeps)",
                "r2": "R2-Gaussian (r2)",
                "gr-paper": "GR-Gaussian, the paper's configuration (gr-paper)",
                "gr-gaussians": "gr's trained Gaussians alone (before its result's steps)",
                "gr": "GR-Gaussian (gr)"}
#: Names in the summary's time line where the first words of METHOD_NAMES are ambiguous.
SHORT_NAMES = {"pdhg-morozov": "PDHG (Morozov)", "pdhg-best": "PDHG (best)",
               "pdhg-cold": "PDHG (cold)", "asd-pocs-best": "ASD-POCS (best)",
               "gr-paper": "GR-Gaussian (paper)", "gr-gaussians": "gr's Gaussians"}
#: Classical methods (every row of theirs competes with gr in the summary's margin).
CLASSICAL = ("fdk", "sart", "asd-pocs", "asd-pocs-best", "pdhg", "pdhg-best", "pdhg-morozov",
             "pdhg-cold", "sart-fixed", "asd-pocs-fixed")
#: Rows that compete in both margins (held-out and fixed): FDK has no sweeps, and the cold
#: PDHG is gr's own classical step run alone.
BOTH_MARGINS = ("fdk", "pdhg-cold")
#: Rows made from another run's record (not runs of their own): name -> (source run, part).
PART_ROWS = {"gr-gaussians": ("gr", "gaussians")}
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


def load_experiment(exp_dir: Path) -> list:
    """The rows of one experiment folder: case, run, category, label, method, views, dir,
    status and ``metrics`` (the run's metrics.json, or None unless the run reads back)."""
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
    return rows


def _experiments(folder: Path) -> dict:
    return {p.name: load_experiment(p) for p in sorted(folder.iterdir())
            if p.is_dir() and p.name != "data"}


def load_runs(out_dir, record=None) -> dict:
    """{experiment: [row]} (``load_experiment``'s rows, then the hybrids' parts as rows).
    With ``record`` (``mi_grg.lab.record``): OUT's finished runs are copied into it first,
    and its runs that OUT has not finished are rows too (marked ``recorded``)."""
    out = Path(out_dir)
    result = _experiments(out) if out.is_dir() else {}
    if record is not None:
        from mi_grg.lab.record import keep, merge
        record = Path(record)
        keep(out, record, result)
        result = merge(result, _experiments(record) if record.is_dir() else {})
    return {exp: rows + part_rows(rows) for exp, rows in result.items() if rows}


def part_rows(rows) -> list:
    """Rows of ``PART_ROWS``: a step of a run's result as a row of its own (its 3-D PSNR
    only, from metrics.json's ``method_info.result.parts``), so a hybrid's parts show in
    the tables beside it."""
    out = []
    for name, (source, part) in PART_ROWS.items():
        for r in rows:
            if r["run"] != source or not r.get("metrics"):
                continue
            info = _dict(_dict(r["metrics"].get("method_info")).get("result"))
            value = _dict(info.get("parts")).get(part)
            if isinstance(value, (int, float)):
                out.append({**r, "run": name, "label": METHOD_NAMES[name],
                            "metrics": {"psnr_3d": float(value)}})
    return out


def _commands(out_dir, record=None) -> list:
    """The commands that made the runs of OUT (and of the record), each once."""
    cmds = []
    for folder in [Path(out_dir)] + ([Path(record)] if record is not None else []):
        for f in sorted(folder.glob("*/runs.json")):
            cmds += [c for c in read_runs(f)["commands"] if c not in cmds]
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
        info = ((r.get("metrics") or {}).get("method_info")) or {}
        fixed = info.get("protocol") == "fixed" and "oracle" in info
        if r["run"] not in CLASSICAL or not (_heldout(r) or fixed):
            continue
        if fixed:       # a fixed count (pdhg-cold) logs its curve too
            chosen = f"lam={info['lam']:g}, {info['iterations']} iterations (fixed)"
        else:
            ch = info.get("chosen") or {}
            setting = ", ".join(f"{k}={v:g}" for k, v in (ch.get("setting") or {}).items())
            chosen = (setting + ", " if setting else "") + f"{ch.get('sweeps')} sweeps"
        o = info.get("oracle") or {}
        best = o.get("psnr_3d_best")
        body.append([r["case"], r["run"], _fmt(_value(r, "psnr_3d"), 2), chosen,
                     f"{_fmt(best, 2)} ({o.get('best_sweep')})" if best is not None else DASH,
                     _fmt(o.get("gap_db"), 2)])
    return header, body


def cold_peak_margin(rows) -> list:
    """[(case, gr − cold PDHG at its best iteration, that iteration)] where pdhg-cold
    logged its curve: the best iteration is picked with the ground truth, a bound that no
    rule reaches, not a result."""
    idx = _index(rows)
    out = []
    for c, _ in _cases(rows):
        g = _value(idx.get((c, "gr")), "psnr_3d")
        o = ((((idx.get((c, "pdhg-cold")) or {}).get("metrics") or {}).get("method_info")
              or {}).get("oracle") or {})
        if g is not None and o.get("psnr_3d_best") is not None:
            out.append((c, g - o["psnr_3d_best"], o["best_sweep"]))
    return out


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
                if m in BOTH_MARGINS or (kind == "heldout") == _heldout(r):
                    pool[m] = p
            if any(m not in BOTH_MARGINS for m in pool):
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
            line.append(DASH if p is None else f"{p:.2f} / {_fmt(s, 3)} / {_fmt_time(t)} s")
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


def _heldout(row) -> bool:
    """Whether a run chose its sweeps (and regularisation) on held-out views."""
    m = (row or {}).get("metrics") or {}
    return (m.get("method_info") or {}).get("protocol") == "heldout"
