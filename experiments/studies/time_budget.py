"""gr / r2 planned to a wall-clock budget (``--option time_budget=SECONDS``, issue 21 item 5).

For each budget, one run on a suite-like case (64^3, 96^2 detector, 25 noisy views, seed 0):
the iterations the plan chose, how long the trainer and the whole reconstruction took
against the budget, the plan's estimate of its loop against the loop's wall clock, and the
3-D PSNR, i.e. a speed-against-error front of the budget option. Run it on a quiet machine,
one run at a time.

    .venv/bin/python experiments/studies/time_budget.py [--phantom shepp] [--method gr] \
        [--budgets 60,150,300]
    .venv/bin/python experiments/studies/time_budget.py --phantom shells --n 128 --budgets 1200 \
        --name time_budget_128        # the 128^3 target (20 min)

Writes docs/bench/NAME.{json,md} (default time_budget); the data set goes to
$TMPDIR/time_budget.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phantom", default="shepp")
    ap.add_argument("--method", default="gr", choices=("gr", "r2"))
    ap.add_argument("--budgets", default="60,150,300", help="seconds, comma-separated")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--name", default="time_budget", help="output name in docs/bench/")
    args = ap.parse_args(argv)
    import mi_grg
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    from mi_grg.methods import code_version
    geo = default_geometry(n=args.n, det=args.n * 3 // 2, views=25)
    case = simulate_case(args.phantom, geo, default_test_angles(25), NoiseModel(), seed=0)
    code = code_version()          # at the start: the code these runs import
    out_root = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "time_budget"
    rows = []
    for b in [float(x) for x in args.budgets.split(",")]:
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        _, m = mi_grg.reconstruct(case, args.method, out_dir=out_root / f"{b:g}",
                                  time_budget=b, progress=False)
        total = time.perf_counter() - t0
        info = m["method_info"]
        plan = info["time_plan"]
        final = [r for r in plan.get("replans", []) if r["final"]]
        rows.append({"budget_s": b, "iterations_planned": plan["iterations"],
                     "window_replans": sum(not r["final"] for r in plan.get("replans", [])),
                     "densify_ended_at": final[0]["at"] if final else None,
                     "final_gaussians": final[0]["n"] if final else None,
                     "iterations_run": info["iterations_run"], "stopped_by": info["stopped_by"],
                     "setup_s": plan["setup_seconds"], "loop_budget_s": plan["loop_budget_seconds"],
                     "loop_estimate_s": plan["estimated_loop_seconds"],
                     "loop_s": round(info["train_seconds"], 2),
                     "reconstruct_s": round(total, 2), "psnr_3d": round(m["psnr_3d"], 2),
                     "ssim_3d": round(m["ssim_3d"], 4), "probe": plan["probe"],
                     "load_1min": round(load, 2)})
        print(json.dumps(rows[-1]))
    result = {"case": f"{args.phantom} {args.n}^3, 25 noisy views", "method": args.method,
              "code": code, "machine": platform.processor() or platform.machine(),
              "cores": os.cpu_count(), "rows": rows}
    (ROOT / "docs" / "bench").mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "bench" / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    (ROOT / "docs" / "bench" / f"{args.name}.md").write_text(markdown(result))
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    lines = [f"# Training to a time budget (`experiments/studies/time_budget.py`)", "",
             f"{r['method']} on {r['case']}; code {r['code']}, {r['cores']} cores; one run "
             "per budget, one at a time (1-minute load average at each start in the JSON).",
             "Loop = the training loop's wall clock (its share of the budget: budget x 0.95 "
             "minus De-Init and probe); reconstruct = the whole `mi_grg.reconstruct` call "
             "(scoring and files included).", "",
             "Iterations: run of first planned; densification: where it ended after how many "
             "re-plans while it was open (each moved the window's end with the plan), and the "
             "count there.", "",
             "| budget (s) | iterations | densification ended | stopped by | setup (s) | "
             "loop: estimate / ran / share (s) | reconstruct (s) | 3-D PSNR | SSIM |",
             "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        dens = (f"at {x['densify_ended_at']} after {x['window_replans']} re-plans, "
                f"{x['final_gaussians']} Gaussians" if x.get("densify_ended_at") else "-")
        lines.append(f"| {x['budget_s']:g} | {x['iterations_run']} of {x['iterations_planned']}"
                     f" | {dens} | {x['stopped_by']} | {x['setup_s']:.1f} | {x['loop_estimate_s']:.0f} / "
                     f"{x['loop_s']:.0f} / {x['loop_budget_s']:.0f} | {x['reconstruct_s']:.0f} | "
                     f"{x['psnr_3d']:.2f} | {x['ssim_3d']:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
