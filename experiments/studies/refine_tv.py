"""gr with and without the TV refinement (``refine="tv"``), against the best fairly tuned
classical method, case by case.

For each case of experiments/studies/fair_baselines.py's data sets (experiments/suite_cpu.json, 64^3, 25
noisy views): gr trains at its defaults without refinement and its final volume and the
state it kept before the held-out views joined are saved ($TMPDIR/refine_tv/CASE, reused
by a later run; with holdout_every=0 the kept state comes from the refinement's decision
run); then ``mi_grg.training.refine.refine_volume`` refines them, which is exactly what
``refine="tv"`` runs after training. Both rows are compared with the best
held-out row of SART, ASD-POCS and PDHG in docs/bench/fair_baselines.json. The 3-D PSNR
against the ground truth is scored here only; no decision reads it.

    MI_GRG_DATA=/work/shared/data .venv/bin/python experiments/studies/refine_tv.py \
        [--cases needles,bone] [--runs DIR] [--option iterations=9000 --tag NAME]

``--option key=value``: gr's training options (e.g. more iterations, holdout_every=0);
``--tag NAME`` writes docs/bench/refine_tv_NAME.* instead; ``--markdown-only`` re-writes the
.md from the .json against today's baselines. Writes docs/bench/refine_tv.{json,md}
after every case (nothing lost on a crash).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "bench" / "refine_tv"
ALL_CASES = "shepp,shepp-parallel,mni152,shell,needles,shells,bone,cement"


def train(case, folder: Path, options: dict) -> dict:
    """gr at its defaults and ``options``, without refinement: final.npy, kept.npy (None
    without a kept state) and info.json in folder."""
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training.config import make_config
    from mi_grg.training.refine import decision_run
    from mi_grg.training.trainer import Trainer
    t0 = time.perf_counter()
    tr = Trainer(case, make_config("gr", None, **{**options, "refine": "none"}),
                 progress=False)
    summary = tr.run()
    final = tr.volume()
    folder.mkdir(parents=True, exist_ok=True)
    if tr.state.kept_raw is not None:
        np.save(folder / "kept.npy", tr.volume(tr.state.kept_raw, tr.state.kept_density_scale))
    elif tr.cfg.protocol.holdout_every == 0:    # refine="tv"'s decision run
        kept, _ = decision_run(tr, progress=False)
        if kept is not None:
            np.save(folder / "kept.npy", kept)
    np.save(folder / "final.npy", final)
    info = {"seconds": time.perf_counter() - t0, "psnr_final": psnr_3d(final, case.vol_gt),
            "kept_it": summary["kept_iteration"], "stopped": summary["stopped_by"],
            "holdout_every": tr.cfg.protocol.holdout_every, "loadavg_1min": os.getloadavg()[0],
            "options": options}
    (folder / "info.json").write_text(json.dumps(info))
    return info


def run_case(name: str, suite, data_root: Path, runs: Path, options: dict) -> dict:
    from mi_grg.data.units import data_range
    from mi_grg.lab.runner import suite_case
    from mi_grg.methods import code_version, score
    from mi_grg.protocol.early_stop import STOP_RULE
    from mi_grg.training.refine import refine_volume
    case = suite_case(suite.case(name), data_root)
    folder = runs / name
    info = (json.loads((folder / "info.json").read_text())
            if (folder / "final.npy").exists() else train(case, folder, options))
    final = np.load(folder / "final.npy")
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    if (folder / "kept.npy").exists():      # without held-out views: the decision run's
        every = info.get("holdout_every", 8) or STOP_RULE.holdout_every
        vol, r = refine_volume(case, np.load(folder / "kept.npy"), final,
                               holdout_every=every, progress=False)
    else:   # no state to decide from: refine="tv" does nothing (it says so)
        vol, r = final, {"lam": 0.0, "iterations": 0, "noise_mse": float("nan"),
                         "heldout_mse": {"start": float("nan"), "refined": float("nan")}}
    seconds = time.perf_counter() - t0
    peak = data_range(case, case.vol_gt)[0]
    before, after = score(final, case.vol_gt, peak), score(vol, case.vol_gt, peak)
    return {"case": name, "gr": before["psnr_3d"], "gr_refined": after["psnr_3d"],
            "ssim": {"gr": before["ssim_3d"], "gr_refined": after["ssim_3d"]}, "lam": r["lam"],
            "iterations": r["iterations"], "heldout_mse": r["heldout_mse"],
            "noise_mse": r["noise_mse"], "weight_candidates": r.get("weight_candidates"),
            "gr_seconds": info["seconds"], "refine_seconds": seconds,
            "loadavg_1min": {"gr": info.get("loadavg_1min"), "refine": load},
            "options": info.get("options", {}),
            "code": code_version()}


def markdown(rows: list, best: dict) -> str:
    lines = ["# gr with the TV refinement (`experiments/studies/refine_tv.py`)", "",
             "Cases of experiments/suite_cpu.json (64^3, 96^2 detector, 25 noisy views), the "
             "data sets of experiments/studies/fair_baselines.py. *best classical*: the best held-out row "
             "of SART, ASD-POCS and PDHG in [fair_baselines.md](fair_baselines.md). lam and "
             "iterations: the refinement's decisions from the kept state on the fitted "
             "views (lam: Morozov's rule, the largest weight whose settled fitted residual "
             "is at most the noise level measured on the held-out views; iterations: the "
             "lowest held-out residual, 0 = unchanged). Held-out MSE: refined / start "
             "(below 1: the refinement predicts the held-out views better). Time: seconds "
             "on a 2-core machine (1-minute load average at each run's start in the JSON).",
             "",
             "| case | gr | gr + refine | best classical | margin gr / gr + refine (dB) | lam | "
             "iterations | held-out MSE refined / start | time gr + refine (s) | code |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = best[r["case"]]
        h = r.get("heldout_mse")      # rows of an earlier rule have none
        ratio = f"{h['refined'] / h['start']:.3f}" if h else "-"
        opts = ", ".join(f"{k}={v}" for k, v in r.get("options", {}).items())
        lines.append(
            f"| {r['case']}{f' ({opts})' if opts else ''} | {r['gr']:.2f} | {r['gr_refined']:.2f} | {b[1]:.2f} ({b[0]}) | "
            f"{r['gr'] - b[1]:+.2f} / {r['gr_refined'] - b[1]:+.2f} | {r['lam']:g} | "
            f"{r['iterations']} | {ratio} | "
            f"{r['gr_seconds']:.0f} + {r['refine_seconds']:.0f} | {r['code']} |")
    if rows:
        m = [r["gr"] - best[r["case"]][1] for r in rows]
        mr = [r["gr_refined"] - best[r["case"]][1] for r in rows]
        lines += ["", f"Mean margin over {len(rows)} case(s): gr {statistics.mean(m):+.2f} dB "
                  f"(behind on {sum(x < 0 for x in m)}), gr + refine "
                  f"{statistics.mean(mr):+.2f} dB (behind on {sum(x < 0 for x in mr)}); mean "
                  f"3-D PSNR {statistics.mean(r['gr'] for r in rows):.2f} -> "
                  f"{statistics.mean(r['gr_refined'] for r in rows):.2f} dB"
                  + (f", mean SSIM {statistics.mean(r['ssim']['gr'] for r in rows):.3f} -> "
                     f"{statistics.mean(r['ssim']['gr_refined'] for r in rows):.3f}"
                     if all("ssim" in r for r in rows) else "") + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=ALL_CASES)
    ap.add_argument("--runs", help="folder of saved gr runs (default $TMPDIR/refine_tv)")
    ap.add_argument("--suite", default=str(ROOT / "experiments" / "suite_cpu.json"))
    ap.add_argument("--option", action="append", default=[], help="key=value (repeat)")
    ap.add_argument("--tag", help="write docs/bench/refine_tv_TAG.* instead")
    ap.add_argument("--markdown-only", action="store_true",
                    help="re-write the .md from the .json (no runs; e.g. after the baselines)")
    args = ap.parse_args(argv)
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parent))   # gr_vs_fair: this folder
    from gr_vs_fair import best_classical, parse_option
    from mi_grg.lab.suite import load_suite
    suite = load_suite(args.suite)
    tmp = Path(os.environ.get("TMPDIR", tempfile.gettempdir()))
    runs = Path(args.runs) if args.runs else tmp / "refine_tv"
    best = best_classical()
    options = dict(parse_option(o) for o in args.option)
    out = OUT.with_name(f"refine_tv_{args.tag}") if args.tag else OUT
    path = out.with_suffix(".json")
    rows = json.loads(path.read_text())["rows"] if path.exists() else []
    for name in ([] if args.markdown_only else args.cases.split(",")):
        row = run_case(name, suite, tmp / "fair_baselines", runs, options)
        rows = [r for r in rows if r["case"] != name] + [row]
        rows.sort(key=lambda r: ALL_CASES.split(",").index(r["case"]))
        path.write_text(json.dumps({"rows": rows}, indent=2, default=float))
        out.with_suffix(".md").write_text(markdown(rows, best))
        print(json.dumps({k: row[k] for k in ("case", "gr", "gr_refined", "lam",
                                              "iterations")}), flush=True)
    out.with_suffix(".md").write_text(markdown(rows, best))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
