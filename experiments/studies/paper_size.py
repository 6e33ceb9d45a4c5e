"""The paper's size on this CPU: gr on a 256^3 case end to end (issue 21: <= 60 min, <= 8 GB).

    .venv/bin/python experiments/studies/paper_size.py [--n 256] [--budget 3300] [--method gr]
    .venv/bin/python experiments/studies/paper_size.py --collect RUN_DIR --time-log LOG [--fdk FDK_DIR]

The run is what a user types (the shepp phantom, 25 noisy cone-beam views of 1.5 n pixels,
25 noise-free test views, seed 0), timed as one process:

    mi-grg simulate --phantom shepp --n 256 --det 384 --views 25 --test-views 25 --out DATA
    mi-grg reconstruct DATA --method gr --option time_budget=3300 --out RUN
    mi-grg reconstruct DATA --method fdk --out FDK_DIR        # the De-Init input, for scale

with the iteration count planned to the budget (``mi_grg.training.budget``; the rule's 6000
iterations at 256^3 were never timed here). Peak memory is the reconstruct process's
maximum resident set size. ``--collect`` tabulates a run made by hand with those commands
under ``/usr/bin/time -v`` (LOG: its output). The paper's own time for its 256^3 cases is
629 s on an RTX 4090 (its Table 3, k = 6, X-3D), for 30k iterations.

Writes docs/bench/paper_size.{json,md}; data and run go to $TMPDIR/paper_size.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAPER = "629 s on an RTX 4090 (paper, Table 3, k = 6, X-3D 256^3, 30k iterations)"


def _cli():
    return [sys.executable, "-m", "mi_grg.cli"]


def run(n: int, budget: float, method: str, work: Path) -> dict:
    data, out = work / "data", work / method
    t0 = time.perf_counter()
    subprocess.run(_cli() + ["simulate", "--phantom", "shepp", "--n", str(n), "--det",
                             str(n * 3 // 2), "--views", "25", "--test-views", "25",
                             "--out", str(data)], check=True)
    t1 = time.perf_counter()
    load = os.getloadavg()[0]
    subprocess.run(_cli() + ["reconstruct", str(data), "--method", method, "--option",
                             f"time_budget={budget:g}", "--out", str(out)], check=True)
    t2 = time.perf_counter()
    # ru_maxrss of the children: the largest of the two processes (KiB on Linux)
    peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20
    subprocess.run(_cli() + ["reconstruct", str(data), "--method", "fdk", "--out",
                             str(work / "fdk")], check=True)
    return {"simulate_s": round(t1 - t0, 1), "reconstruct_wall_s": round(t2 - t1, 1),
            "peak_rss_gib": round(peak_gib, 2), "load_1min": round(load, 2),
            **_metrics(out), "fdk": _fdk(work / "fdk")}


def _fdk(out: Path | None):
    if out is None:
        return None
    m = json.loads((out / "metrics.json").read_text())
    return {"psnr_3d": round(m["psnr_3d"], 2), "ssim_3d": round(m["ssim_3d"], 4),
            "seconds": round(m["seconds"], 1)}


def collect(run_dir: Path, time_log: Path, fdk_dir: Path | None) -> dict:
    text = time_log.read_text(errors="replace")
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", text)
    if not (rss and wall):
        raise SystemExit(f"{time_log}: no /usr/bin/time -v report found")
    secs = 0.0
    for part in wall.group(1).split(":"):
        secs = 60 * secs + float(part)
    return {"reconstruct_wall_s": round(secs, 1),
            "peak_rss_gib": round(int(rss.group(1)) / 2**20, 2), **_metrics(run_dir),
            "fdk": _fdk(fdk_dir)}


def _metrics(out: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    info = m["method_info"]
    plan = info.get("time_plan") or {}
    replans = plan.get("replans", [])
    window = [r for r in replans if not r.get("final")]
    final = [r for r in replans if r.get("final")]
    return {"method": m["method"], "code": m["machine"]["mi_grg"], "grid": m["nVoxel"],
            "psnr_3d": round(m["psnr_3d"], 2), "ssim_3d": round(m["ssim_3d"], 4),
            "seconds": round(m["seconds"], 1), "train_seconds": round(info["train_seconds"], 1),
            "iterations_run": info["iterations_run"], "stopped_by": info["stopped_by"],
            "first_plan": plan.get("iterations"),
            "last_plan": replans[-1]["iterations"] if replans else plan.get("iterations"), "setup_s": plan.get("setup_seconds"),
            "window_replans": len(window),
            "densification_ended_at": final[0]["at"] if final else None,
            "final_gaussians": final[0]["n"] if final else None,
            "seconds_per_iteration": final[0]["seconds_per_iteration"] if final else None}


def markdown(r: dict) -> str:
    x = r["result"]
    return "\n".join([
        "# The paper's size on this CPU (`experiments/studies/paper_size.py`)", "",
        f"{x['method']} on shepp {r['n']}^3 (25 noisy cone-beam views of {r['n'] * 3 // 2}^2, "
        f"seed 0), `--option time_budget={r['budget']:g}`; code {x['code']}, "
        f"{r['cores']} cores ({r['machine']}), one process, nothing else running.", "",
        "| | |", "|---|---|",
        f"| reconstruct, wall clock (De-Init, training, volume, scores, files) | "
        f"{x['reconstruct_wall_s'] / 60:.1f} min ({x['reconstruct_wall_s']:.0f} s) |",
        f"| of which training (metrics.json train_seconds) | {x['train_seconds']:.0f} s |",
        f"| peak memory (max RSS) | {x['peak_rss_gib']:.2f} GiB |",
        f"| iterations: first plan -> last plan -> run | {x['first_plan']} -> "
        f"{x['last_plan']} -> {x['iterations_run']} |",
        f"| stopped by | {x['stopped_by']} |",
        f"| densification: re-plans while open, ended at | {x['window_replans']}, "
        f"iteration {x['densification_ended_at']} ({x['final_gaussians']} Gaussians) |",
        f"| seconds per iteration after densification | {x['seconds_per_iteration']} |",
        f"| 3-D PSNR / SSIM | {x['psnr_3d']:.2f} dB / {x['ssim_3d']:.3f} |",
        (f"| FDK on the same data (De-Init's input) | {x['fdk']['psnr_3d']:.2f} dB / "
         f"{x['fdk']['ssim_3d']:.3f}, {x['fdk']['seconds']:.1f} s |" if x.get("fdk") else
         "| FDK on the same data | not run |"),
        f"| the paper | {PAPER} |", ""])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--budget", type=float, default=3300.0, help="time_budget, seconds")
    ap.add_argument("--method", default="gr", choices=("gr", "r2"))
    ap.add_argument("--collect", type=Path, help="a finished run's folder (with --time-log)")
    ap.add_argument("--time-log", type=Path, help="/usr/bin/time -v output of that run")
    ap.add_argument("--fdk", type=Path, help="with --collect: an fdk run on the same data")
    args = ap.parse_args(argv)
    if args.collect:
        if not args.time_log:
            ap.error("--collect needs --time-log")
        result = collect(args.collect, args.time_log, args.fdk)
    else:
        work = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "paper_size"
        result = run(args.n, args.budget, args.method, work)
    r = {"n": args.n, "budget": args.budget, "machine": platform.processor() or platform.machine(),
         "cores": os.cpu_count(), "result": result}
    (ROOT / "docs" / "bench").mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "bench" / "paper_size.json").write_text(json.dumps(r, indent=1))
    (ROOT / "docs" / "bench" / "paper_size.md").write_text(markdown(r))
    print(markdown(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
