"""The refinement's cap (``refine_max_iterations``): gr's result from one trained state per
case with the default cap and with wider ones, and where each run's time goes.

The refinement's length is a held-out choice within the cap (mi_grg.training.result); on
needles at 64^3 and 128^3 the choice fell on the cap. Here each case trains once (gr's
defaults, ``field_result.make_case``), then ``result.finish`` runs with each cap on that
same state: export (= vol_pred) 3-D PSNR, the length chosen, and the seconds of training,
the length's decision, the final refinement and the fit back into the Gaussians. Tuning
cases choose; confirmation cases only report.

    MI_GRG_DATA=/work/shared/data python experiments/studies/refine_cap.py \\
        --cases needles shepp needles7 shells7 --caps 200 800 --data /tmp/field_data

Writes docs/bench/refine_cap.json (merged per case) and .md. One process at a time: the
seconds are the timing of a run alone on this machine.
"""
import argparse
import json
import time
from pathlib import Path

from field_result import CASES, ROOT, make_case, save_record


def run_case(name: str, caps, data_root: Path, n: int) -> dict:
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    from mi_grg.training.config import TrainConfig, make_config
    from mi_grg.training.trainer import Trainer
    case, which = make_case(name, n, data_root)
    t0 = time.perf_counter()
    cfg = make_config("gr")
    tr = Trainer(case, cfg, progress=False)
    summary = tr.run()
    rec = {"case": name, "set": which, "n": n, "train_seconds": time.perf_counter() - t0,
           "n_gaussians": summary["n_gaussians"], "default_cap": cfg.protocol.refine_max_iterations,
           "caps": {}}
    for cap in caps:
        tr.cfg = TrainConfig.from_flat({**cfg.to_flat(), "refine_max_iterations": int(cap)})
        t0 = time.perf_counter()
        vol, _, info = result.finish(tr, progress=False)
        ref = info.get("refine", {})
        rec["caps"][str(cap)] = {
            "psnr": float(psnr_3d(vol, case.vol_gt)), "seconds": time.perf_counter() - t0,
            "iterations": ref.get("iterations"), "at_cap": ref.get("at_cap"),
            "decision_seconds": ref.get("decision_seconds"),
            "final_seconds": ref.get("final_seconds"),
            "fit_seconds": (ref.get("fit") or {}).get("seconds"),
            "parts": info["parts"],
            "heldout_mse": ref.get("heldout_mse")}
    tr.cfg = cfg
    return rec


def markdown(records: dict) -> str:
    rows = ["| case | n | set | cap | export (= vol_pred) dB | length chosen | at cap | "
            "train s | result s (decision + final + fit) |", "|---|---|---|---|---|---|---|---|---|"]
    for which in ("tuning", "confirmation"):
        for r in (r for r in records.values() if r["set"] == which):
            for cap, c in sorted(r["caps"].items(), key=lambda kv: int(kv[0])):
                parts = " + ".join("-" if c[k] is None else f"{c[k]:.0f}" for k in
                                   ("decision_seconds", "final_seconds", "fit_seconds"))
                rows.append(f"| {r['case']} | {r['n']} | {which} | {cap} | {c['psnr']:.2f} | "
                            f"{c['iterations']} | {'yes' if c['at_cap'] else 'no'} | "
                            f"{r['train_seconds']:.0f} | {c['seconds']:.0f} ({parts}) |")
    for which in ("tuning", "confirmation"):
        # the cases of this set measured with every cap of the widest comparison
        rs = [r for r in records.values() if r["set"] == which and len(r["caps"]) > 1]
        caps = sorted({int(k) for r in rs for k in r["caps"]})
        rs = [r for r in rs if all(str(k) in r["caps"] for k in caps)]
        if rs and len(caps) > 1:
            d = caps[0]
            gains = ", ".join(
                f"cap {k}: {sum(r['caps'][str(k)]['psnr'] - r['caps'][str(d)]['psnr'] for r in rs) / len(rs):+.2f} dB"
                for k in caps[1:])
            rows.append(f"\nMean change over cap {d}, {which} ({len(rs)} cases): {gains}.")
    return "\n".join(rows) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["needles", "shepp", "needles7", "shells7"],
                    choices=list(CASES))
    ap.add_argument("--caps", nargs="+", type=int, default=[200, 800])
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--data", type=Path, default=Path("/tmp/field_result_data"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "refine_cap")
    a = ap.parse_args()
    for name in a.cases:
        rec = run_case(name, a.caps, a.data, a.n)
        save_record(a.out, f"{name}_{a.n}", rec, markdown)
        print(json.dumps({k: v for k, v in rec.items() if k != "caps"}),
              {k: (v["psnr"], v["iterations"]) for k, v in rec["caps"].items()}, flush=True)

if __name__ == "__main__":
    main()
