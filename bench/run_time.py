"""A gr run's wall clock, split into its steps: training, the refinement's length decision,
the final refinement, the fit back and the rest (data loading, 3-D logging, writing).

    .venv/bin/python bench/run_time.py results/cpu128/data/shepp --label shepp128 \
        [--method gr] [--option log_3d_every=150 ...]
    .venv/bin/python bench/run_time.py --record results/cpu128/table1/shepp/gr --label NAME

The first form runs ``mi-grg reconstruct DATA --method M --out TMP`` in a subprocess and
records it: start nothing else meanwhile, the point is the time of a run alone (the load
average before and after is kept to show it). The second records a finished run's
metrics.json as it is (its load is unknown). Each row is merged by its label into
docs/bench/run_time.json; docs/bench/run_time.md is rewritten from it.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "bench" / "run_time"


def row(metrics: dict, **extra) -> dict:
    """The time split of one run's metrics.json (seconds; None where a step did not run)."""
    info = metrics.get("method_info", {})
    refine = info.get("refine") or {}
    fit = refine.get("fit") or {}
    steps = {"training": info.get("train_seconds"),
             "decision": refine.get("decision_seconds"),
             "final": refine.get("final_seconds"),
             "fit": fit.get("seconds")}
    total = float(metrics["seconds"])
    counted = sum(v for v in steps.values() if v is not None)
    return {"case": (metrics.get("data", {}).get("suite_case") or {}).get("name"),
            "n": metrics.get("nVoxel"), "method": metrics.get("method"),
            "options": {k: v for k, v in metrics.get("options", {}).items() if k != "out_dir"},
            "code": metrics.get("machine", {}).get("mi_grg"),
            "machine": metrics.get("machine"), "total": total, **steps,
            "rest": total - counted, "psnr_3d": metrics.get("psnr_3d"),
            "n_gaussians": info.get("n_gaussians"),
            "refine_iterations": refine.get("iterations"),
            "decision_curve_lengths": {k: c[-1][0] for k, c in
                                       (refine.get("anchor", {}).get("curves") or {}).items()},
            **extra}


def run(data: str, method: str, options: list) -> dict:
    """Run reconstruct alone in a subprocess; its row with the load before and after."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "mi_grg.cli", "reconstruct", data, "--method", method,
               "--out", str(Path(tmp) / "run")]
        for o in options:
            cmd += ["--option", o]
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True)
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()[0]
        metrics = json.loads((Path(tmp) / "run" / "metrics.json").read_text())
    return row(metrics, process_wall=wall, load_before=load0, load_after=load1,
               recorded=time.strftime("%Y-%m-%d %H:%M"))


def write(rows: dict) -> None:
    OUT.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    f = lambda v: "-" if v is None else f"{v:.0f}"      # noqa: E731
    lines = ["# A gr run's time, split into its steps (`bench/run_time.py`)", "",
             "Seconds of wall clock (metrics.json's own step times; \"rest\": loading, 3-D "
             "logging, writing). Load: 1-minute load average before / after the run "
             "(\"-\": a finished run recorded afterwards, its load unknown).", "",
             "| label | case | code | total | training | length decision (curves' lengths) "
             "| final refinement | fit back | rest | 3-D PSNR | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, r in rows.items():
        lens = ", ".join(f"{k} {v}" for k, v in r.get("decision_curve_lengths", {}).items())
        load = ("-" if r.get("load_before") is None
                else f"{r['load_before']:.2f} / {r['load_after']:.2f}")
        lines.append(f"| {label} | {r['case']} {'x'.join(map(str, r['n'] or []))} | "
                     f"{r['code']} | {f(r['total'])} | {f(r['training'])} | "
                     f"{f(r['decision'])} ({lens or '-'}) | {f(r['final'])} | {f(r['fit'])} | "
                     f"{f(r['rest'])} | {r['psnr_3d']:.2f} | {load} |")
    OUT.with_suffix(".md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="?", help="a case folder to reconstruct alone")
    ap.add_argument("--record", help="a finished run's folder (its metrics.json) instead")
    ap.add_argument("--label", required=True)
    ap.add_argument("--method", default="gr")
    ap.add_argument("--option", action="append", default=[])
    a = ap.parse_args(argv)
    if (a.data is None) == (a.record is None):
        ap.error("give a case folder to run, or --record RUN_DIR")
    path = OUT.with_suffix(".json")
    rows = json.loads(path.read_text()) if path.exists() else {}
    if a.record:
        rows[a.label] = row(json.loads((Path(a.record) / "metrics.json").read_text()))
    else:
        rows[a.label] = run(a.data, a.method, a.option)
    write(rows)
    print(OUT.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
