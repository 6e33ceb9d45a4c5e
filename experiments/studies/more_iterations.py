"""More iterations with today's result: gr's defaults against the same run with ``factor``
times the size rule's iteration count (the schedule's horizon unchanged), each trained and
finished (voxel average, refinement, fit back) on the same data.

The target (issue: "the Gaussians carry the result"): 3x the iterations scores at least the
default's 3-D PSNR minus 0.1 dB. Cases: ``field_result.make_case`` (tuning and
confirmation sets as there); both runs in one process, one after the other.

    MI_GRG_DATA=/work/shared/data python experiments/studies/more_iterations.py \\
        --cases needles shepp --factors 1 3 --data /tmp/field_data

Writes docs/bench/more_iterations.json (merged per case) and .md.
"""
import argparse
import json
import time
from pathlib import Path

from field_result import CASES, ROOT, make_case, save_record


def run_case(name: str, factors, data_root: Path, n: int) -> dict:
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    from mi_grg.training.config import iterations_for_size, make_config
    from mi_grg.training.trainer import Trainer
    case, which = make_case(name, n, data_root)
    base = iterations_for_size(max(case.geometry.nVoxel))
    rec = {"case": name, "set": which, "n": n, "default_iterations": base, "runs": {}}
    for f in factors:
        cfg = make_config("gr") if f == 1 else make_config("gr", iterations=int(f * base))
        t0 = time.perf_counter()
        tr = Trainer(case, cfg, progress=False)
        summary = tr.run()
        train_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        vol, _, info = result.finish(tr, progress=False)
        rec["runs"][str(f)] = {
            "iterations": int(f * base), "iterations_run": summary.get("iterations_run"),
            "psnr": float(psnr_3d(vol, case.vol_gt)), "gaussians_alone":
            info["parts"].get("gaussians"), "n_gaussians": summary["n_gaussians"],
            "train_seconds": train_s, "result_seconds": time.perf_counter() - t0,
            "refine_iterations": info.get("refine", {}).get("iterations")}
    return rec


def markdown(records: dict) -> str:
    rows = ["| case | n | set | iterations | export (= vol_pred) dB | minus the default | "
            "Gaussians alone dB | Gaussians | train + result s |", "|---|---|---|---|---|---|---|---|---|"]
    for which in ("tuning", "confirmation"):
        for r in (r for r in records.values() if r["set"] == which):
            d = r["runs"].get("1", {}).get("psnr")
            for f, x in sorted(r["runs"].items(), key=lambda kv: float(kv[0])):
                diff = "-" if d is None else f"{x['psnr'] - d:+.2f}"
                rows.append(f"| {r['case']} | {r['n']} | {which} | {x['iterations']} ({f}x) | "
                            f"{x['psnr']:.2f} | {diff} | {x['gaussians_alone']:.2f} | "
                            f"{x['n_gaussians']} | {x['train_seconds']:.0f} + "
                            f"{x['result_seconds']:.0f} |")
    return "\n".join(rows) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["needles", "shepp"], choices=list(CASES))
    ap.add_argument("--factors", nargs="+", type=float, default=[1, 3])
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--data", type=Path, default=Path("/tmp/field_result_data"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "more_iterations")
    a = ap.parse_args()
    factors = [int(f) if float(f).is_integer() else f for f in a.factors]
    for name in a.cases:
        rec = run_case(name, factors, a.data, a.n)
        save_record(a.out, f"{name}_{a.n}", rec, markdown)
        print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
