"""PDHG's weight rule and iteration cap, chosen on tuning cases and confirmed on others.

For each case and each lam of a half-decade grid, two PDHG runs from zero, each evaluated
every ``EVAL_EVERY`` iterations up to ``--max-iter``:

- on the fitted views (the held-out split of ``STOP_RULE``): the held-out views' per-view
  PSNR and mean squared residual, and the fitted views' residual, exactly what
  ``mi_grg.protocol.heldout`` reads;
- on every view: the 3-D PSNR (the oracle surface: the best weight and iteration count).

Every rule is then replayed on those curves with the package's own decision code
(``EarlyStopper`` and ``heldout._choose``, the log grid widening from ``LAM_GRID``): the
rule's choice (lam, sweeps) is read off the all-view curve. That replays ``run_heldout``
without running it once per rule and cap. Caps: fixed ones, and ``widen:<gain>``
(the package's cap widening, ``mi_grg.protocol.widening``, at that gain).

    MI_GRG_DATA=/work/shared/data .venv/bin/python experiments/studies/pdhg_rules.py \\
        --cases shepp,needles --max-iter 600 [--n 64]

Writes docs/bench/pdhg_rules.json (curves and choices, merged per case) and
docs/bench/pdhg_rules.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "bench"
#: name: (source, seed, set). Tuning cases choose; confirmation cases only report.
CASES = {
    "shepp": ("shepp", 0, "tuning"), "needles": ("needles", 0, "tuning"),
    "shells": ("shells", 0, "tuning"), "bone": ("bone_128.npy", 0, "tuning"),
    "needles7": ("needles", 7, "confirmation"), "shells7": ("shells", 7, "confirmation"),
    "shells11": ("shells", 11, "confirmation"),
    "cement": ("cement_128.npy", 0, "confirmation"),
    "mni152": ("mni152_128.npy", 0, "confirmation"),
}
LAMS = (0.0001, 0.0003, 0.001, 0.003, 0.01, 0.03, 0.1)
FIXED_CAPS = (60, 120, 240, 480)
WIDEN_GAINS = (0.02, 0.05, 0.1, 0.2, 0.5)
RULE_NAMES = ("best", "one_se", "one_se_paired", "morozov", "disc_best", "disc_one_se")
#: |log(recorded lam / grid lam)| up to which a recorded curve stands in for a grid value.
NEAR = 0.12


def _case(name: str, n: int, data_root: Path):
    from field_result import make_case
    return make_case(name, n, data_root, CASES)


def curves(name: str, n: int, lams, max_iter: int, data_root: Path, on_lam=None,
           recorded=None) -> dict:
    """The fitted-view and all-view curves of every lam (module docstring); ``on_lam(rec)``
    after each lam (so an interrupted study keeps what it measured). ``recorded``: an earlier
    record of the same case and ``max_iter``, whose lams are kept and not run again."""
    from mi_grg.classical.pdhg import EVAL_EVERY, PDHG, operator_norm
    from mi_grg.classical.iterative import _to_numpy
    from mi_grg.core.joseph import JosephProjector, forward_project
    from mi_grg.evaluation.metrics import psnr_3d, psnr_proj_views
    from mi_grg.protocol.discrepancy import mse
    from mi_grg.protocol.early_stop import STOP_RULE
    from mi_grg.protocol.split import decision_split
    case, which = _case(name, n, data_root)
    geo = case.geometry
    ang = np.asarray(geo.angles, np.float64)
    fit, held = decision_split(geo.n_views, STOP_RULE.holdout_every, "pdhg")
    gfit = geo.with_angles(ang[fit])
    norms = {"fit": operator_norm(JosephProjector(gfit), gfit.angles, 8),
             "all": operator_norm(JosephProjector(geo), geo.angles, 8)}
    rec = {"case": name, "set": which, "n": n, "eval_every": EVAL_EVERY,
           "max_iter": max_iter, "lams": {}}
    if recorded is not None and (recorded["max_iter"], recorded["eval_every"]) == (
            max_iter, EVAL_EVERY):
        rec["lams"] = dict(recorded["lams"])
    for lam in lams:
        if repr(float(lam)) in rec["lams"]:
            continue
        t0 = time.perf_counter()
        s = PDHG(case.train[fit], gfit, gfit.angles, lam=lam, norm_A=norms["fit"])
        views, held_mse, fit_mse = [], [], []
        for it in range(1, max_iter + 1):
            s.step()
            if it % EVAL_EVERY:
                continue
            vol = _to_numpy(s.x, gfit)
            pred = forward_project(vol, geo, ang[held])
            views.append(psnr_proj_views(pred, case.train[held]).tolist())
            held_mse.append(mse(pred, case.train[held]))
            fit_mse.append(mse(forward_project(vol, gfit, gfit.angles), case.train[fit]))
        t_fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        s = PDHG(case.train, geo, geo.angles, lam=lam, norm_A=norms["all"])
        p3 = []
        for it in range(1, max_iter + 1):
            s.step()
            if it % EVAL_EVERY == 0:
                p3.append(float(psnr_3d(_to_numpy(s.x, geo), case.vol_gt)))
        rec["lams"][repr(float(lam))] = {
            "heldout_views": views, "heldout_mse": held_mse, "fit_mse": fit_mse,
            "psnr_3d": p3, "seconds_fit": t_fit, "seconds_all": time.perf_counter() - t0}
        if on_lam is not None:
            on_lam(rec)
        print(f"{name} lam {lam:g}: best 3-D {max(p3):.2f} at {EVAL_EVERY * (1 + int(np.argmax(p3)))}"
              f" ({t_fit:.0f} + {time.perf_counter() - t0:.0f} s)", flush=True)
    return rec


# ---------------------------------------------------------------- replaying the rules
def default_cap(n: int) -> int:
    """PDHG's default held-out cap on an n^3 grid (``mi_grg.classical.pdhg.heldout_cap``)."""
    from types import SimpleNamespace
    from mi_grg.classical.pdhg import heldout_cap
    return heldout_cap(SimpleNamespace(nVoxel=(n, n, n)))


def _candidate(c: dict, lam: float, cap, ee: int, rule: str, base: int) -> dict:
    """What ``heldout._decision_run`` returns for one lam, from its curves, with ``cap``
    a number of sweeps or "widen:<gain dB>" (``mi_grg.protocol.widening``, from ``base``)."""
    from mi_grg.protocol.early_stop import STOP_RULE
    from mi_grg.protocol.widening import Widening
    widening = (Widening(base, gain_db=float(cap.split(":")[1]))
                if isinstance(cap, str) else None)
    stopper = STOP_RULE.stopper()
    per_view, residuals, last = [], [], 0
    limit = len(c["heldout_views"]) * ee
    for i, views in enumerate(c["heldout_views"]):
        sweep = (i + 1) * ee
        if widening is None and sweep > cap:
            break
        last = sweep
        residuals.append([sweep, c["heldout_mse"][i], c["fit_mse"][i]])
        per_view.append([sweep, views])
        stop = stopper.update(sweep, float(np.nanmean(views))) == "stop"
        if stop and rule != "morozov":
            break
        if widening is not None and not widening.goes_on(stopper.history, sweep):
            break
        if sweep >= limit:
            last = None       # the recorded curve ended before the rule did
    values = dict(stopper.history)
    return {"setting": {"lam": lam}, "sweeps_run": last, "kept_sweep": stopper.kept_iteration,
            "rule_sweep": stopper.kept_iteration,
            "heldout_psnr": values[stopper.kept_iteration], "history": stopper.history,
            "heldout_psnr_views": per_view, "residuals": residuals}


def _one_se_paired(cands: list) -> int:
    """A candidate rule (not in the package): the one-standard-error rule with the standard
    error of each candidate's per-view PSNR difference to the best (paired over the same
    held-out views) instead of the spread of the best's per-view PSNRs."""
    from mi_grg.protocol.heldout import _choose
    best = _choose(cands, False, "best", False)[0]

    def views(c):
        return np.asarray(dict((s, v) for s, v in map(tuple, c["heldout_psnr_views"]))[
            c["kept_sweep"]], np.float64)
    vb = views(cands[best])
    order = sorted(range(len(cands)), key=lambda i: cands[i]["setting"]["lam"])
    within = []
    for i in order:
        d = vb - views(cands[i])
        se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
        if float(np.mean(d)) <= se:
            within.append(i)
    return within[-1]


def replay(rec: dict, rule: str, cap) -> dict:
    """The rule's choice on ``rec``'s curves, widening the grid as ``LogGrid`` does."""
    from mi_grg.classical.iterative import GRID_EXTEND
    from mi_grg.classical.pdhg import LAM_GRID
    from mi_grg.protocol.heldout import _choose
    from mi_grg.protocol.search import LogGrid
    ee = rec["eval_every"]
    have = {float(k): v for k, v in rec["lams"].items()}
    grid = LogGrid("lam", list(LAM_GRID), max_extend=GRID_EXTEND,
                   rule={"one_se_paired": "one_se"}.get(rule, rule.replace("disc_", "")))
    pending, cands, near = list(grid.values), [], False
    while pending:
        for lam in pending:
            # the grid widens by 3.33 past 0.01 and 3 below 0.001: the nearest recorded lam
            # within NEAR stands in for it (said in the record)
            key = min(have, key=lambda k: abs(math.log(k / lam)))
            if abs(math.log(key / lam)) > NEAR:
                return {"rule": rule, "cap": cap, "error": f"lam {lam:g} not recorded"}
            near |= abs(math.log(key / lam)) > 1e-6
            cands.append(_candidate(have[key], key, cap, ee, rule, default_cap(rec["n"])))
            cands[-1]["grid_lam"] = lam
        if rule == "one_se_paired":
            chosen = _one_se_paired(cands)
        elif rule.startswith("disc_"):      # sweeps by the discrepancy principle
            chosen = _choose(cands, True, rule[5:], False)[0]
        else:
            chosen = _choose(cands, False, rule, False)[0]
        nxt = grid.next_value(cands[chosen]["grid_lam"])
        pending = [] if nxt is None else [nxt]
    pick = cands[chosen]
    lam, k = pick["setting"]["lam"], int(pick["kept_sweep"])
    p3 = have[lam]["psnr_3d"]
    if k // ee > len(p3):
        return {"rule": rule, "cap": cap, "error": f"sweep {k} past the recorded curve"}
    runs = [c["sweeps_run"] for c in cands]
    return {"rule": rule, "cap": cap, "lam": lam, "sweeps": k, "psnr_3d": p3[k // ee - 1],
            "iterations": None if None in runs else sum(runs) + k,
            "incomplete": None in runs, "nearest_lam_stood_in": near}


def oracle(rec: dict, cap=None) -> dict:
    """The best lam and iteration count by the ground truth (within ``cap``)."""
    ee, best = rec["eval_every"], (-math.inf, None, None)
    for key, c in rec["lams"].items():
        p = c["psnr_3d"][: None if cap is None else cap // ee]
        i = int(np.argmax(p))
        best = max(best, (p[i], float(key), (i + 1) * ee))
    return {"psnr_3d": best[0], "lam": best[1], "sweeps": best[2]}


def summarise(recs: list) -> dict:
    """Every rule at every cap on every case; means per set and grid size (``means`` keyed
    "tuning, 64^3")."""
    caps = list(FIXED_CAPS) + [f"widen:{g:g}" for g in WIDEN_GAINS]
    out = {"cases": {}, "means": {}}
    for r in recs:
        o = oracle(r)
        row = {"set": r["set"], "n": r["n"], "oracle": o, "oracle_60": oracle(r, 60),
               "oracle_at_default_cap": oracle(r, default_cap(r["n"])), "rules": {}}
        for rule in RULE_NAMES:
            for cap in caps:
                row["rules"][f"{rule}@{cap}"] = replay(r, rule, cap)
        out["cases"][f"{r['case']}_{r['n']}"] = row
    for n in sorted({v["n"] for v in out["cases"].values()}):
        for which in ("tuning", "confirmation"):
            rows = [v for v in out["cases"].values() if v["set"] == which and v["n"] == n]
            if not rows:
                continue
            m = {"oracle": statistics.mean(v["oracle"]["psnr_3d"] for v in rows)}
            for key in rows[0]["rules"]:
                vals = [v["rules"][key].get("psnr_3d") for v in rows]
                if None not in vals:
                    m[key] = statistics.mean(vals)
            out["means"][f"{which}, {n}^3"] = m
    return out


def markdown(summary: dict) -> str:
    lines = ["# PDHG's weight rule and iteration cap (`experiments/studies/pdhg_rules.py`)",
             "", "3-D PSNR (dB) of PDHG from zero under each rule (lam by the rule on the "
             "fitted views, sweeps by the held-out stop rule unless said), replayed on "
             "recorded curves (`rule@cap`: the cap fixed, or `widen:g`, doubled while a "
             "doubling gains more than g dB of held-out PSNR); in brackets lam and "
             "iterations; *oracle* = the best lam and iteration count chosen with the "
             "ground truth (within the recorded iterations). Tuning cases chose the "
             "default; confirmation cases only report it. Rules: best (best held-out "
             "PSNR), one_se (one standard error of the best's per-view PSNRs), "
             "one_se_paired (of the paired per-view differences; a candidate, not in the "
             "package), morozov, disc_* (sweeps by the discrepancy principle, lam by the "
             "rule after it).", ""]
    cases = summary["cases"]
    keys = list(next(iter(cases.values()))["rules"])
    for n in sorted({v["n"] for v in cases.values()}):
        lines += _summary_at(summary, n)
    rules = list(dict.fromkeys(k.split("@")[0] for k in keys))
    for rule in rules:
        cols = [k for k in keys if k.split("@")[0] == rule]
        lines += [f"## {rule}", "", "| case | set | oracle (lam, it.) | " + " | ".join(
            k.split("@")[1] for k in cols) + " |", "|---|---|---|" + "---|" * len(cols)]
        for name, v in cases.items():
            o = v["oracle"]
            cells = []
            for k in cols:
                r = v["rules"][k]
                cells.append(r["error"] if "error" in r else
                             f"{r['psnr_3d']:.2f} ({r['lam']:g}, {r['sweeps']})")
            lines.append(f"| {name} | {v['set']} | {o['psnr_3d']:.2f} ({o['lam']:g}, "
                         f"{o['sweeps']}) | " + " | ".join(cells) + " |")
        for which, m in summary["means"].items():
            lines.append(f"| **mean, {which}** | | {m['oracle']:.2f} | " + " | ".join(
                f"{m[k]:.2f}" if k in m else "-" for k in cols) + " |")
        lines.append("")
    return "\n".join(lines) + "\n"


def _count(k: int) -> str:
    return f"{k} case" if k == 1 else f"{k} cases"


def _summary_at(summary: dict, n: int) -> list:
    """On the n^3 cases at PDHG's default cap there: each rule's mean per set, and its mean
    distance to the best rule of each case (the per-case maximum over the rules that every
    case could replay); then the oracle within that cap and at any recorded count."""
    cap = str(default_cap(n))
    cases = {k: v for k, v in summary["cases"].items() if v["n"] == n}
    rules = [r for r in RULE_NAMES
             if all("psnr_3d" in v["rules"][f"{r}@{cap}"] for v in cases.values())]
    sets = [w for w in ("tuning", "confirmation") if any(v["set"] == w for v in cases.values())]
    lines = [f"## Summary at {n}^3, cap {cap} (the default there)", "",
             "Mean 3-D PSNR (dB) per set; in brackets the mean distance to the best of these "
             "rules on each case.", "",
             "| rule | " + " | ".join(
                 f"{w} ({_count(sum(v['set'] == w for v in cases.values()))})" for w in sets)
             + " |", "|---|" + "---|" * len(sets)]
    if not rules:
        return lines[:-3] + ["No rule could be replayed on every case (a lam it needs was not "
                             "recorded).", ""]
    best = {k: max(v["rules"][f"{r}@{cap}"]["psnr_3d"] for r in rules)
            for k, v in cases.items()}
    for rule in rules:
        cells = []
        for which in sets:
            vs = [(k, v) for k, v in cases.items() if v["set"] == which]
            got = [v["rules"][f"{rule}@{cap}"]["psnr_3d"] for _, v in vs]
            cells.append(f"{statistics.mean(got):.2f} "
                         f"({statistics.mean(g - best[k] for g, (k, _) in zip(got, vs)):+.2f})")
        lines.append(f"| {rule} | " + " | ".join(cells) + " |")
    for label, key in ((f"oracle within {cap}", "oracle_at_default_cap"),
                       ("oracle, any recorded count", "oracle")):
        cells = []
        for which in sets:
            vs = [(k, v) for k, v in cases.items() if v["set"] == which]
            got = [v[key]["psnr_3d"] for _, v in vs]
            cells.append(f"{statistics.mean(got):.2f} "
                         f"({statistics.mean(g - best[k] for g, (k, _) in zip(got, vs)):+.2f})")
        lines.append(f"| *{label}* | " + " | ".join(cells) + " |")
    return lines + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="shepp,needles")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--max-iter", type=int, default=600)
    ap.add_argument("--lams", default=",".join(map(str, LAMS)))
    ap.add_argument("--data", default=os.environ.get("TMPDIR", "/tmp") + "/pdhg_rules")
    ap.add_argument("--markdown-only", action="store_true")
    args = ap.parse_args(argv)
    path = OUT / "pdhg_rules.json"
    store = json.loads(path.read_text()) if path.exists() else {"curves": {}}
    if not args.markdown_only:
        import mi_grg  # noqa: F401  (first: it points Dr.Jit at a suitable LLVM)
        import mitsuba as mi
        mi.set_variant("llvm_ad_mono")
        for name in args.cases.split(","):
            def save(rec, key=f"{name}_{args.n}"):
                store["curves"][key] = rec
                path.write_text(json.dumps(store))
            save(curves(name, args.n, [float(x) for x in args.lams.split(",")],
                        args.max_iter, Path(args.data), save,
                        store["curves"].get(f"{name}_{args.n}")))
    store["summary"] = summarise(list(store["curves"].values()))
    path.write_text(json.dumps(store))
    (OUT / "pdhg_rules.md").write_text(markdown(store["summary"]))
    print(markdown(store["summary"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
