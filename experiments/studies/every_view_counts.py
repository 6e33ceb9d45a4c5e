"""Every view counts (issue 26): gr and r2 with the default view protocol against
``holdout_every=0`` (no held-out views: every view trains all run and nothing decides),
over the cases of a suite's Table 1.

The default runs are Table 1's (``mi-grg experiment table1 --suite S --out OUT``); this
script runs their ``holdout_every=0`` twins on the same data (OUT's data sets) with the same
options, one at a time with every core, under OUT/every_view/<case>/<method>/ (a finished
twin is not rerun: nothing lost on a crash), and writes docs/bench/every_view_counts.{json,md}.
Target (issue 26): the default within 0.1 dB of ``holdout_every=0`` on average.

    .venv/bin/python experiments/studies/every_view_counts.py --out results/cpu [--cases shepp,needles] \\
        [--methods gr,r2] [--variant holdout_until=0.667 [--variant KEY=VALUE ...]]

``--variant KEY=VALUE`` (repeatable) measures a candidate protocol without making it the
default: it runs
Table 1's gr / r2 again with that option added (under OUT/every_view_KEY_VALUE/, resumable)
and scores those runs, instead of Table 1's, against the same twins; results in
docs/bench/every_view_counts_KEY_VALUE.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TARGET_DB = 0.1
#: options of the default run that say where and how it ran, not what it computed
RUN_ONLY = ("out_dir", "progress")


def _metrics(path: Path):
    return json.loads(path.read_text()) if path.exists() else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/cpu", help="the suite experiment's OUT")
    ap.add_argument("--cases", default=None, help="default: every case with Table 1 runs")
    ap.add_argument("--methods", default="gr,r2")
    ap.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                    help="a candidate protocol option, run on top of Table 1's options "
                         "(repeat for several)")
    ap.add_argument("--markdown-only", action="store_true",
                    help="re-write the .md from the existing .json (no runs)")
    args = ap.parse_args(argv)
    bench = ROOT / "docs" / "bench"
    from mi_grg.cli import _parse_options      # the parser of `--option KEY=VALUE`
    variant = _parse_options(args.variant)
    tag = "_".join(v.replace("=", "_") for v in args.variant) or None
    candidate = ", ".join(args.variant) or None
    stem = "every_view_counts" + (f"_{tag}" if tag else "")
    if args.markdown_only:
        result = json.loads((bench / f"{stem}.json").read_text())
        (bench / f"{stem}.md").write_text(markdown(result))
        return 0
    import mi_grg
    from mi_grg.data.dataset import load_case
    from mi_grg.lab.suite import load_suite
    from mi_grg.methods import code_version, reconstruct
    out = Path(args.out)
    suite = load_suite(out / "suite.json")
    t1 = out / "table1"
    cases = (args.cases.split(",") if args.cases else
             [c.name for c in suite.cases if (t1 / c.name).is_dir()])
    rows = []
    for name in cases:
        spec = suite.case(name)
        for method in args.methods.split(","):
            default = _metrics(t1 / name / method / "metrics.json")
            if default is None:
                raise SystemExit(f"no Table 1 run {t1 / name / method}: run `mi-grg "
                                 f"experiment table1 --suite SUITE --out {out}` first")
            run_dir = out / "every_view" / name / method
            twin = _metrics(run_dir / "metrics.json")
            load = os.getloadavg()[0]
            opts = {k: v for k, v in default["options"].items() if k not in RUN_ONLY}
            if twin is None:
                case = load_case(out / "data" / spec.data_dir_name)
                _, twin = reconstruct(case, method, out_dir=str(run_dir), progress=False,
                                      **{**opts, "holdout_every": 0})
            if variant:     # the candidate replaces Table 1's run as "default"
                var_dir = out / f"every_view_{tag}" / name / method
                default = _metrics(var_dir / "metrics.json")
                if default is None:
                    load = os.getloadavg()[0]
                    case = load_case(out / "data" / spec.data_dir_name)
                    _, default = reconstruct(case, method, out_dir=str(var_dir),
                                             progress=False, **{**opts, **variant})
            views = default["method_info"].get("views") or {}
            rows.append({"case": name, "method": method,
                         "default": {k: default[k] for k in ("psnr_3d", "ssim_3d", "seconds")},
                         "holdout_every_0": {k: twin[k] for k in ("psnr_3d", "ssim_3d",
                                                                    "seconds")},
                         "delta_db": default["psnr_3d"] - twin["psnr_3d"],
                         "default_stop": views.get("stop"),
                         "default_code": default["machine"].get("mi_grg"),
                         "twin_code": twin["machine"].get("mi_grg"),
                         "loadavg_1min": load})
            print(json.dumps({k: rows[-1][k] for k in ("case", "method", "delta_db")}),
                  flush=True)
            write(rows, mi_grg.variant(), code_version(), stem, candidate)  # after each run
    print(markdown(write(rows, mi_grg.variant(), code_version(), stem, candidate)))
    return 0


def write(rows: list, variant: str, code: str, stem: str = "every_view_counts",
          candidate: str | None = None) -> dict:
    by = {}
    for r in rows:
        by.setdefault(r["method"], []).append(r["delta_db"])
    from mi_grg.training.config import TrainConfig
    result = {"machine": {"variant": variant, "cores": os.cpu_count(), "mi_grg": code},
              "candidate": candidate, "default_holdout_until":
                  TrainConfig().protocol.holdout_until,
              "rows": rows, "target_db": TARGET_DB,
              "mean_delta_db": {m: statistics.mean(v) for m, v in by.items()},
              "mean_delta_db_all": statistics.mean(r["delta_db"] for r in rows)}
    bench = ROOT / "docs" / "bench"
    bench.mkdir(parents=True, exist_ok=True)
    (bench / f"{stem}.json").write_text(json.dumps(result, indent=2, default=str))
    (bench / f"{stem}.md").write_text(markdown(result))
    return result


def markdown(result: dict) -> str:
    cand = result.get("candidate")
    default = ("the Table 1 run (one training view in 8 held out, evenly spread, for the "
               f"stop rule until {result.get('default_holdout_until', 0.75)} x the budget, "
               "then trained)" if not cand else
               f"Table 1's options with `{cand}` added (bench `--variant`)")
    lines = ["# Every view counts: " + (f"the candidate `{cand}`" if cand else
                                        "the default view protocol")
             + " against `holdout_every=0` (`experiments/studies/every_view_counts.py`)", "",
             f"Variant {result['machine']['variant']}, {result['machine']['cores']} cores, "
             f"one run at a time; default = {default}, twin = the same data "
             "and options with `holdout_every=0` (all 25 views train all run). Code of each "
             "run in the JSON. delta = default − twin (3-D PSNR).", "",
             "| case | method | default PSNR / SSIM / s | `holdout_every=0` PSNR / SSIM / s "
             "| delta (dB) |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        d, t = r["default"], r["holdout_every_0"]
        lines.append(f"| {r['case']} | {r['method']} | {d['psnr_3d']:.2f} / "
                     f"{d['ssim_3d']:.3f} / {d['seconds']:.0f} | {t['psnr_3d']:.2f} / "
                     f"{t['ssim_3d']:.3f} / {t['seconds']:.0f} | {r['delta_db']:+.2f} |")
    lines += ["", "Mean delta: " + ", ".join(
        f"{m} {v:+.3f} dB" for m, v in result["mean_delta_db"].items())
        + f"; all {result['mean_delta_db_all']:+.3f} dB over {len(result['rows'])} cells "
        f"(target: >= -{result['target_db']} dB)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
