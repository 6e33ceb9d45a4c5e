"""The results report: markdown tables and plots from an experiments directory.

    mi-grg report --out results/cpu --report docs/results.md

Reads ``OUT/<experiment>/runs.json`` (written by ``mi_grg.lab.runner``) and each run's
``metrics.json`` / ``train_log.csv`` / ``progress_log.csv``; writes the markdown file and
its PNGs under ``<report dir>/img/<report name>/``. Only numbers found in those files appear in
our tables; a missing or failed run shows as "—". The paper's numbers are transcribed from
its tables and labelled as such (its own data, X-3D at 256^3 / 512^2, not comparable case by
case).

Where it lives: ``report_tables`` (loading, the tables, the paper's tables),
``report_figures`` (the figures); this module writes the prose around them.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_grg.lab.report_figures import (anytime_table, heldout_rows, montage,
                                       plot_iterations, plot_speed, views_table_and_plot)
from mi_grg.lab.report_tables import (_cases, CLASSICAL, classical_margin, cold_peak_margin,
                                      _commands, complete_cases, DASH, _fmt_time, _index,
                                      load_runs, _md_table,
                                      _mean_all, METHOD_NAMES, METHOD_ORDER, oracle_rows,
                                      _paper_fmt, paper_table1_md, PAPER_TABLE2,
                                      PAPER_TABLE3_K, PAPER_TABLE3_SIGMA, per_case_rows,
                                      _runs_summary, SEED_METRICS, seeds_table,
                                      SHORT_NAMES, _sweep_table, table1_rows, _value,
                                      PART_ROWS)
from mi_grg.lab.report_tables import PAPER_TABLE1  # noqa: F401  (a public name, as before)


# ---------------------------------------------------------------------------- summary
def summary_lines(out_dir, rows=None) -> list:
    """Three lines for the README: where gr wins, where not, at what time cost (Table 1 of
    ``out_dir``, or its ``rows`` when given)."""
    rows = load_runs(out_dir).get("table1", []) if rows is None else rows
    idx = _index(rows)
    cases = [c for c, _ in _cases(rows)]
    wins, losses, vs_r2, unmatched = [], [], [], []
    for c in cases:
        g = _value(idx.get((c, "gr")), "psnr_3d")
        others = {m: _value(idx.get((c, m)), "psnr_3d") for m in METHOD_ORDER
                  if m not in ("gr", *PART_ROWS) and not m.endswith("-fixed")}
        others = {m: v for m, v in others.items() if v is not None}
        if g is None or not others:
            continue
        if others.get("r2") is not None:
            vs_r2.append(g - others["r2"])
        if not any(m in CLASSICAL for m in others):
            # "best" against other Gaussian rows only would read as a lead over every method
            unmatched.append(c)
            continue
        best_m = max(others, key=others.get)
        (wins if g > others[best_m] else losses).append((c, best_m, g - others[best_m]))
    if not wins and not losses:
        return ["No Table 1 runs with both gr and a classical method yet: no summary."]
    line1 = (f"GR-Gaussian (gr) has the best 3-D PSNR on {len(wins)} of "
             f"{len(wins) + len(losses)} cases"
             + (f" ({', '.join(f'{c} +{d:.2f} dB' for c, _, d in wins)})" if wins else "")
             + (f"; against R2-Gaussian it is {np.mean(vs_r2):+.2f} dB on average "
                f"(better on {sum(d > 0 for d in vs_r2)} of {len(vs_r2)})" if vs_r2 else "")
             + (f"; left out, no classical row among these runs: {', '.join(unmatched)}"
                if unmatched else "")
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
    line3 = (f"Mean time per case{over}: " + ", ".join(parts) + ratio
             + _result_steps_time(idx, done, times.get("gr")) + ".")
    return [line1, line2, line3, margin_line(rows)]


def _result_steps_time(idx, done, gr_mean) -> str:
    """Of gr's mean time, its result's steps (method_info.result.seconds) and the rest
    (De-Init, training, its decisions): a run resumed to redo only the result's steps adds
    the earlier call's wall clock to its time, so the split says where each came from."""
    steps = [((idx.get((c, "gr")) or {}).get("metrics") or {}).get("method_info", {})
             .get("result", {}).get("seconds") for c in done]
    if gr_mean is None or not steps or any(not isinstance(t, (int, float)) for t in steps):
        return ""
    t = float(np.mean(steps))
    return (f"; of gr's {_fmt_time(gr_mean)} s, training {_fmt_time(gr_mean - t)} s and "
            f"the result's steps {_fmt_time(t)} s")


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
    peak = cold_peak_margin(rows)
    if peak:
        line += (f"; against cold PDHG at gr's weight at its best iteration (picked with the "
                 f"ground truth, a bound no rule reaches): "
                 f"{np.mean([d for _, d, _ in peak]):+.2f} dB (" + ", ".join(
                     f"{c} {d:+.2f} at {k}" for c, d, k in peak) + ")")
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


def _intro_md(out: Path, report: Path, all_rows: dict, record: Path | None) -> list:
    """The report's head: how to regenerate it, what the numbers mean, summary, setup."""
    again = f"mi-grg report --out {out} --report {report}" + (
        f" --record {record}" if record is not None else "")
    md = ["# Results", "",
          f"Generated by `{again}` from the runs in `{out}`"
          + (f" and the record `{record}`" if record is not None else "")
          + ". Regenerate everything with:", "", "```"]
    md += _commands(out, record) + [again, "```", ""]
    kept = sorted({(exp, r["case"]) for exp, rows in all_rows.items() for r in rows
                   if r.get("recorded")})
    if kept:
        md += [f"From the record (`{record}`: each run's metrics.json as it was recorded; "
               "their volumes were not kept, so no new figure shows them; their cases keep "
               "the figures of the report before): "
               + ", ".join(f"{exp}/{case}" for exp, case in kept) + ".", ""]
    md += ["Our numbers: 3-D PSNR (dB) and SSIM of the reconstructed volume against the "
           "simulated ground truth, R2-Gaussian's convention (data range 1, SSIM over 2-D "
           "slices), mean over cases; time = wall-clock seconds of the whole reconstruction. "
           f"\"{DASH}\" = no result (run missing or failed); a mean needs every case.", ""]
    md += ["## Summary", ""] + [f"{i + 1}. {s}" for i, s in
                                enumerate(summary_lines(out, all_rows.get("table1", [])))]
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
                   "a log grid widened until the choice is interior; every other rule has "
                   "its row (-best: the best held-out PSNR; pdhg-morozov: Morozov's "
                   "discrepancy principle), and gr is measured against the best of them on "
                   "each case. pdhg-cold is gr's classical step alone: PDHG from zero at "
                   "gr's refinement weight, five times the refinement's cap; gr-gaussians "
                   "is gr's trained field alone, before its result's steps (from gr's own "
                   "record, not a run). The \"fixed\" rows run "
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


def _extremes_md(t1, out: Path, img_dir: Path, rel: str, earlier=None) -> list:
    """Montages of the best and worst case by gr's 3-D PSNR (``earlier``: as in
    ``mi_grg.lab.compare.kept_figure``)."""
    from mi_grg.lab.compare import kept_figure
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
            name = f"montage_{which}_{case}.png"
            png = (kept_figure(t1, case, name, img_dir, earlier)
                   or montage(out, t1, case, img_dir / name))
            if png is not None:
                md += [f"{which.capitalize()} case by gr's 3-D PSNR (or the best method's "
                       f"where gr is missing): **{case}**", "",
                       f"![{which} {case}]({rel}/{png.name})", ""]
        md += ["Every run also has its own `slices.png` (three central slices, ground truth, "
               "|error|) in its directory under " f"`{out}`.", ""]
    else:
        md += [f"{DASH}", ""]
    return md


def write_report(out_dir, report_path="docs/results.md", record=None) -> Path:
    """Write the markdown report (and its PNGs under <report dir>/img/<report name>/), built
    beside them and swapped in whole; never over what the runner wrote
    (``mi_grg.lab.finished.report_target``). With ``record``, OUT's finished runs are
    copied into that record first and the record's others are counted too
    (``mi_grg.lab.record``)."""
    from mi_grg.data.outputs import staged_report
    from mi_grg.lab.finished import report_target
    from mi_grg.lab.record import check_record
    out, report = Path(out_dir), Path(report_path)
    record = None if record is None else Path(record)
    if record is not None:
        check_record(record, out, report)
    all_rows = load_runs(out, record)
    img_dir = report_target(out, report, all_rows, record)
    rel = os.path.relpath(img_dir, report.parent)
    with staged_report(report, img_dir) as (tmp_report, tmp_img):
        _write_md(out, report, all_rows, tmp_report, tmp_img, rel, record, earlier=img_dir)
    return report


def _write_md(out: Path, report: Path, all_rows: dict, path: Path, img_dir: Path,
              rel: str, record: Path | None = None, earlier: Path | None = None) -> None:
    """The report of ``all_rows`` into ``path``, its PNGs into ``img_dir`` (``earlier``: the
    image folder of the report it replaces, whose figures of the record's cases it keeps)."""
    from mi_grg.lab.compare import comparison_section
    from mi_grg.lab.finished import broken_md
    t1 = all_rows.get("table1")
    md = _intro_md(out, report, all_rows, record)
    md += _table1_md(t1, out)
    md += _table2_md(all_rows.get("table2"), out)
    md += _table3_md(all_rows.get("table3"), out)
    md += _iterations_md(all_rows.get("iterations"), out, img_dir, rel)
    md += _speed_md(all_rows.get("speed"), t1, out, img_dir, rel)
    md += _views_md(all_rows.get("views"), out, img_dir, rel)
    md += _seeds_md(all_rows.get("seeds"), out)
    md += comparison_section(out, t1, img_dir, rel, earlier)
    md += _extremes_md(t1, out, img_dir, rel, earlier)
    md += broken_md(all_rows)
    path.write_text("\n".join(md) + "\n")
