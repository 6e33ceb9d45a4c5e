"""Held-out-stopped classical baselines against their oracle.

For suite-like cases (64^3, 96^2 detector, 25 noisy views, the cases of
experiments/suite_cpu.json), runs SART, ASD-POCS and PDHG with their default protocol
(sweep count and regularisation chosen on held-out training views, then the chosen
setting run on all views; mi_grg.protocol.heldout) and, for reference, the
paper's fixed 10 sweeps. Records per run the 3-D PSNR of the result, the oracle (the best
3-D PSNR over the chosen setting's sweeps on all views, chosen with the ground truth; it
decides nothing) and the time of the result (the oracle's extra sweeps and scoring
excluded). Targets (issue 22): held-out-stopped ASD-POCS and PDHG within 0.5 dB of their
oracle on average, at most 30 s per 64^3 case.

    MI_GRG_DATA=/work/shared/data .venv/bin/python experiments/studies/fair_baselines.py \
        [--cases shepp,needles,bone] [--reps 1] [--runs sart,asd-pocs,pdhg]

(volume cases such as bone read their source volume from $MI_GRG_DATA.)

Writes docs/bench/fair_baselines.{json,md}; the data sets go to $TMPDIR/fair_baselines.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUNS = [("sart", "sart", {}), ("asd-pocs", "asd-pocs", {}), ("pdhg", "pdhg", {}),
        ("pdhg-morozov", "pdhg", {"lam_rule": "morozov"}),
        ("pdhg-200", "pdhg", {"n_iter": 200}),     # whether the 60 cap holds PDHG back
        ("sart-fixed", "sart", {"n_iter": 10, "stop": "none"}),
        ("asd-pocs-fixed", "asd-pocs", {"n_iter": 10, "stop": "none"})]
TARGET_GAP_DB, TARGET_SECONDS = 0.5, 30.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="shepp,needles,bone")
    ap.add_argument("--reps", type=int, default=1, help="repetitions (times: median)")
    ap.add_argument("--runs", default=",".join(r for r, _, _ in RUNS),
                    help="which runs (comma list of: " + ", ".join(r for r, _, _ in RUNS) + ")")
    ap.add_argument("--suite", default=str(ROOT / "experiments" / "suite_cpu.json"))
    ap.add_argument("--markdown-only", action="store_true",
                    help="re-write the .md from the existing .json (no runs)")
    args = ap.parse_args(argv)
    if args.markdown_only:
        result = json.loads((ROOT / "docs" / "bench" / "fair_baselines.json").read_text())
        (ROOT / "docs" / "bench" / "fair_baselines.md").write_text(markdown(result))
        print(markdown(result))
        return 0
    from mi_grg.lab.runner import suite_case
    from mi_grg.lab.suite import load_suite
    from mi_grg.methods import code_version, reconstruct
    suite = load_suite(args.suite)
    data_root = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "fair_baselines"
    path = ROOT / "docs" / "bench" / "fair_baselines.json"
    old = json.loads(path.read_text()) if path.exists() else {"rows": []}
    rows = [{"code": old["machine"]["mi_grg"], **r} for r in old["rows"]]   # kept rows
    for name in args.cases.split(","):
        case = suite_case(suite.case(name), data_root)
        for run, method, opts in [r for r in RUNS if r[0] in args.runs.split(",")]:
            secs, load = [], []
            for _ in range(max(1, args.reps)):
                load.append(os.getloadavg()[0])
                _, m = reconstruct(case, method, progress=False, **opts)
                info = m.get("method_info") or {}
                secs.append(m["seconds"])     # the oracle's time is not in it
            row = {"case": name, "run": run, "method": method, "options": opts,
                   "psnr_3d": m["psnr_3d"], "ssim_3d": m["ssim_3d"],
                   "seconds": statistics.median(secs), "seconds_all": secs,
                   "loadavg_1min": load}
            if info.get("protocol") == "heldout":
                o = info.get("oracle") or {}
                row.update(chosen=info["chosen"], oracle_best=o.get("psnr_3d_best"),
                           oracle_sweep=o.get("best_sweep"), gap_db=o.get("gap_db"),
                           search=info.get("search"),
                           decision_seconds=info["decision_seconds"],
                           final_seconds=info["final_seconds"],
                           candidates=[{k: c[k] for k in ("setting", "kept_sweep",
                                                          "sweeps_run", "heldout_psnr")}
                                       for c in info["candidates"]])
            row["code"] = code_version()
            rows = [r for r in rows if (r["case"], r["run"]) != (name, run)] + [row]
            cases = list(dict.fromkeys(r["case"] for r in rows))
            order = [r for r, _, _ in RUNS]
            rows.sort(key=lambda r: (cases.index(r["case"]), order.index(r["run"])))
            print(json.dumps({k: row.get(k) for k in ("case", "run", "psnr_3d", "seconds",
                                                      "gap_db", "chosen")}), flush=True)
        write(rows, args)          # after every case: nothing lost on a crash
    print(markdown(write(rows, args)))
    return 0


def write(rows: list, args) -> dict:
    """Summarise ``rows`` and write docs/bench/fair_baselines.{json,md}; returns the JSON."""
    import mi_grg
    from mi_grg.methods import code_version
    summary = {}
    for run in ("sart", "asd-pocs", "pdhg", "pdhg-morozov"):
        sel = [r for r in rows if r["run"] == run and r.get("gap_db") is not None]
        if sel:
            summary[run] = {"mean_gap_db": statistics.mean(r["gap_db"] for r in sel),
                            "max_seconds": max(r["seconds"] for r in sel),
                            "mean_psnr_3d": statistics.mean(r["psnr_3d"] for r in sel)}
    result = {"machine": {"variant": mi_grg.variant(), "cores": os.cpu_count(),
                          "mi_grg": code_version()},
              "cases": sorted({r["case"] for r in rows}, key=[r["case"] for r in rows].index),
              "reps": args.reps, "rows": rows,
              "summary": summary,
              "targets": {"gap_db": TARGET_GAP_DB, "seconds": TARGET_SECONDS}}
    out = ROOT / "docs" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "fair_baselines.json").write_text(json.dumps(result, indent=2, default=float))
    (out / "fair_baselines.md").write_text(markdown(result))
    return result


def _f(v, d=2):
    return "—" if v is None else f"{v:.{d}f}"


def markdown(result: dict) -> str:
    lines = ["# Fair classical baselines: held-out stopping vs the oracle "
             "(`experiments/studies/fair_baselines.py`)", "",
             f"Cases {', '.join(result['cases'])} of experiments/suite_cpu.json (64^3, 96^2 "
             f"detector, 25 noisy views); variant {result['machine']['variant']}, "
             f"{result['machine']['cores']} cores (shared: the 1-minute load average at "
             f"each run's start is in the JSON), code {', '.join(sorted({r.get('code', result['machine']['mi_grg']) for r in result['rows']}))} (each row's in the JSON); "
             f"{result['reps']} repetition(s), median time.", "",
             "Held-out rows (the default): sweeps and regularisation chosen without the "
             "ground truth on the training views, one in 8 held out (evenly spread), then the chosen "
             "setting run on all 25 views. PDHG: gr's early-stopping rule on the held-out "
             "PSNR. SART / ASD-POCS: the discrepancy principle, the first sweep whose fitted-"
             "view residual reaches the noise level measured on the held-out views (the "
             "lowest held-out mean squared residual). The TV weights (ASD-POCS's alpha at its "
             "discrepancy sweep, PDHG's lam at its kept iteration) by the one-standard-error "
             "rule: the largest weight whose held-out PSNR lies within one standard error "
             "(over the held-out views) of the best (mi_grg.protocol.heldout); pdhg-morozov: PDHG's "
             "lam by Morozov's discrepancy principle instead (the largest weight whose fitted "
             "residual at the iteration cap is at most the noise level), its iterations by "
             "the lowest held-out residual, the rule of gr's TV refinement. **Oracle** = the best 3-D PSNR "
             "over the chosen setting's sweeps on all views, picked with the ground truth "
             "(reported only; it decides nothing); gap = oracle − result. Time = the "
             "result's wall-clock seconds (the held-out decision included; the oracle's "
             "extra sweeps and scoring excluded). Fixed rows: the paper's 10 sweeps at "
             "TIGRE's defaults.", "",
             "**Weights tried**: the TV weight's search on a half-decade log grid, widened past "
             "the end the rule chose (mi_grg.protocol.search); *interior* = the chosen "
             "weight has a tried neighbour on both sides.", "",
             "| case | run | 3-D PSNR | SSIM | oracle (sweep) | gap (dB) | chosen | "
             "weights tried | time (s) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        ch = r.get("chosen")
        chosen = (", ".join([f"{k}={v:g}" for k, v in ch["setting"].items()]
                            + [f"{ch['sweeps']} sweeps"]) if ch else "")
        oracle = (f"{_f(r.get('oracle_best'))} ({r.get('oracle_sweep')})"
                  if r.get("oracle_best") is not None else "")
        s = r.get("search")
        tried = (f"{', '.join(f'{v:g}' for v in s['values_tried'])} "
                 f"({'interior' if s['interior'] else 'EDGE'})" if s else "")
        lines.append(f"| {r['case']} | {r['run']} | {_f(r['psnr_3d'])} | "
                     f"{_f(r['ssim_3d'], 3)} | {oracle} | {_f(r.get('gap_db'))} | {chosen} | "
                     f"{tried} | {r['seconds']:.1f} |")
    lines += ["", "Summary (held-out rows; targets: mean gap <= "
              f"{result['targets']['gap_db']} dB, <= {result['targets']['seconds']:g} s "
              "per case):", "", "| method | mean 3-D PSNR | mean gap to oracle (dB) | "
              "max time (s) |", "|---|---|---|---|"]
    for run, s in result["summary"].items():
        lines.append(f"| {run} | {_f(s['mean_psnr_3d'])} | {_f(s['mean_gap_db'])} | "
                     f"{s['max_seconds']:.1f} |")
    from mi_grg.classical.iterative import HELDOUT_SWEEP_CAP
    from mi_grg.classical.pdhg import HELDOUT_ITERATION_CAP
    cands = [(r["run"], c) for r in result["rows"] for c in r.get("candidates") or []]
    at_cap = sum(c["sweeps_run"] >= (HELDOUT_ITERATION_CAP if run.startswith("pdhg")
                                     else HELDOUT_SWEEP_CAP) for run, c in cands)
    lines += ["", f"The held-out PSNR rule stopped {len(cands) - at_cap} of the "
              f"{len(cands)} candidate runs before the sweep cap ({HELDOUT_SWEEP_CAP} sweeps "
              f"for SART / ASD-POCS, {HELDOUT_ITERATION_CAP} iterations for PDHG); the others "
              "ran to the cap with the held-out PSNR still rising or within 0.5 % of its "
              "best. Held-out views measure how well projections are predicted; the 3-D "
              "error of SART and ASD-POCS grows after a few sweeps through noise amplified "
              "along directions that project weakly, which no held-out projection predicts, "
              "so on these noisy cases that rule alone cannot see their semi-convergence "
              "(it landed SART 4.51 dB and ASD-POCS 2.72 dB from their oracles on average, "
              "code 5c8f7f1). The discrepancy principle sees it: fitting the training views "
              "below the noise level fits noise. PDHG's TV minimiser does not semi-converge, "
              "and there the held-out PSNR rule lands near its oracle."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
