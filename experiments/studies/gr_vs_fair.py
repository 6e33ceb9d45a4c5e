"""gr (or r2) against the best fairly tuned classical method, case by case.

The cases and their data are experiments/studies/fair_baselines.py's (experiments/suite_cpu.json, 64^3,
25 noisy views, the same simulated data sets), so each gr run is compared with the best
held-out row of SART, ASD-POCS and PDHG in docs/bench/fair_baselines.json: every decision
on held-out training views, none on the ground truth.

    MI_GRG_DATA=/work/shared/data .venv/bin/python experiments/studies/gr_vs_fair.py \
        [--cases shepp,needles,shells] [--method gr] [--label default] \
        [--option lambda_tv=0.2 ...] [--config scenes/gr_paper.xml]

Rows accumulate in docs/bench/gr_vs_fair.json, one per (case, label); a rerun of a
(case, label) replaces it. docs/bench/gr_vs_fair.md is rewritten from the JSON after every
run (nothing lost on a crash). Volume cases (bone, cement, mni152, shell) read their
source volume from $MI_GRG_DATA.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "bench" / "gr_vs_fair"
FAIR = ROOT / "docs" / "bench" / "fair_baselines.json"
CLASSICAL = ("sart", "asd-pocs", "pdhg", "pdhg-morozov", "pdhg-200")
ALL_CASES = "shepp,shepp-parallel,mni152,shell,needles,shells,bone,cement"


def parse_option(text: str) -> tuple:
    """``key=value`` -> (key, value) with value as int, float, bool or str."""
    if "=" not in text:
        raise SystemExit(f"--option {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    for cast in (int, float):
        try:
            return key, cast(raw)
        except ValueError:
            pass
    return key, {"true": True, "false": False}.get(raw.lower(), raw)


def best_classical() -> dict:
    """case -> (run, 3-D PSNR) of the best held-out classical row of fair_baselines."""
    rows = json.loads(FAIR.read_text())["rows"]
    best = {}
    for r in rows:
        if r["run"] in CLASSICAL and r["psnr_3d"] > best.get(r["case"], ("", -1e9))[1]:
            best[r["case"]] = (r["run"], r["psnr_3d"])
    return best


def load_rows() -> list:
    path = OUT.with_suffix(".json")
    return json.loads(path.read_text())["rows"] if path.exists() else []


def run_case(name: str, args, suite, data_root: Path) -> dict:
    from mi_grg.lab.runner import suite_case
    from mi_grg.methods import code_version, reconstruct
    case = suite_case(suite.case(name), data_root)
    opts = dict(parse_option(o) for o in args.option)
    if args.config:
        opts["config"] = args.config
    load = os.getloadavg()[0]
    _, m = reconstruct(case, args.method, progress=False, **opts)
    info = m.get("method_info") or {}
    return {"case": name, "label": args.label, "method": args.method, "options": opts,
            "psnr_3d": m["psnr_3d"], "ssim_3d": m["ssim_3d"], "seconds": m["seconds"],
            "iterations": f"{info.get('iterations_run')}/{info.get('iterations_planned')}",
            "stopped_by": info.get("stopped_by"), "n_gaussians": info.get("n_gaussians"),
            "loadavg_1min": load, "code": code_version()}


def summary(rows: list, best: dict) -> dict:
    """label -> mean margin over the best classical method, cases behind, mean time."""
    out = {}
    for label in dict.fromkeys(r["label"] for r in rows):
        sel = [r for r in rows if r["label"] == label and r["case"] in best]
        margins = [r["psnr_3d"] - best[r["case"]][1] for r in sel]
        out[label] = {"cases": len(sel), "mean_margin_db": statistics.mean(margins),
                      "behind": sum(m < 0 for m in margins),
                      "mean_psnr_3d": statistics.mean(r["psnr_3d"] for r in sel),
                      "max_seconds": max(r["seconds"] for r in sel)}
    return out


def markdown(rows: list, best: dict) -> str:
    lines = ["# gr against the best fairly tuned classical method (`experiments/studies/gr_vs_fair.py`)",
             "", "Cases of experiments/suite_cpu.json (64^3, 96^2 detector, 25 noisy views), "
             "the data sets of experiments/studies/fair_baselines.py; *best classical* = the best held-out "
             "row of SART, ASD-POCS and PDHG in [fair_baselines.md](fair_baselines.md) "
             "(weights by the one-standard-error rule on held-out views). margin = gr − best "
             "classical, 3-D PSNR in dB. Time: wall-clock seconds on a 2-core machine; the "
             "1-minute load average at each run's start is in the JSON (other work shared "
             "the machine where it exceeds 2).", "",
             "| case | label | options | 3-D PSNR | best classical | margin (dB) | "
             "iterations | time (s) | code |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (ALL_CASES.split(",").index(r["case"])
                                          if r["case"] in ALL_CASES else 99, r["label"])):
        b = best.get(r["case"])
        opts = ", ".join(f"{k}={v}" for k, v in r["options"].items()) or "defaults"
        lines.append(f"| {r['case']} | {r['label']} | {opts} | {r['psnr_3d']:.2f} | "
                     + (f"{b[1]:.2f} ({b[0]}) | {r['psnr_3d'] - b[1]:+.2f}" if b else "— | —")
                     + f" | {r['iterations']} | {r['seconds']:.0f} | {r['code']} |")
    lines += ["", "| label | cases | mean 3-D PSNR | mean margin (dB) | cases behind | "
              "max time (s) |", "|---|---|---|---|---|---|"]
    for label, s in summary(rows, best).items():
        lines.append(f"| {label} | {s['cases']} | {s['mean_psnr_3d']:.2f} | "
                     f"{s['mean_margin_db']:+.2f} | {s['behind']} | {s['max_seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def write(rows: list) -> None:
    best = best_classical()
    OUT.with_suffix(".json").write_text(json.dumps(
        {"rows": rows, "summary": summary(rows, best)}, indent=2, default=float))
    OUT.with_suffix(".md").write_text(markdown(rows, best))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=ALL_CASES)
    ap.add_argument("--method", default="gr", choices=("gr", "r2"))
    ap.add_argument("--label", default="default", help="the row label of this setting")
    ap.add_argument("--option", action="append", default=[], help="key=value (repeat)")
    ap.add_argument("--config", help="a training XML config (e.g. scenes/gr_paper.xml)")
    ap.add_argument("--suite", default=str(ROOT / "experiments" / "suite_cpu.json"))
    args = ap.parse_args(argv)
    from mi_grg.lab.suite import load_suite
    suite = load_suite(args.suite)
    data_root = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "fair_baselines"
    for name in args.cases.split(","):
        row = run_case(name, args, suite, data_root)
        rows = [r for r in load_rows()
                if (r["case"], r["label"]) != (name, args.label)] + [row]
        write(rows)
        print(json.dumps({k: row[k] for k in ("case", "label", "psnr_3d", "seconds")}),
              flush=True)
    print(OUT.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
