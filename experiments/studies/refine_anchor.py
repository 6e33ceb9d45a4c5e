"""The refinement's anchor: gr's TV refinement with the anchor and without it, from one
trained state per case, and whether the run's own views can tell which is better.

The refinement (mi_grg.training.result) solves min 1/2 ||A x - b'||^2 + lambda TV(x) from the
field's voxelisation, with b' = b - (P(G) - A V(G)) ("anchored") or b' = b ("plain"). For
each case and each form: the length the held-out views choose (from the state kept before
they joined, on the fitted views, as ``result.decide_length``) and its held-out residual;
the grid that length gives from the returned field on every view (3-D PSNR) and the grid
after 400 iterations (converged); and the **export check**: from the kept state, the
chosen refinement on the fitted views, fitted back into the Gaussians
(``distill.fit_to_volume``) and projected exactly onto the held-out views, its residual
there. A rule can only use the residuals; the 3-D PSNRs say which form was right.

    MI_GRG_DATA=/work/shared/data python experiments/studies/refine_anchor.py \\
        --cases bone needles shepp --states /tmp/refine_anchor_states --data /tmp/field_data \\
        [--finish]

``--finish`` also makes the result with the package's defaults (``refine_anchor="auto"``)
and records its export; ``--finish-only`` adds that to a case's existing record. ``--states``: each case's trained run (checkpoint) is kept there and resumed, not trained
again. Writes docs/bench/refine_anchor.json (merged per case) and .md.
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np

from field_result import CASES, ROOT, make_case, save_record

CONVERGED = 400


def _grid(x, geo):
    return np.asarray(x.numpy(), np.float32).reshape(geo.nVoxel)


def decide(tr, case, anchor: bool) -> dict:
    """``result.decide_length`` for the anchored or plain data, with what the export check
    needs (the kept field, its voxelisation, the fitted and held-out views)."""
    from mi_grg.training import result
    geo = case.geometry
    kept, _, decider = result.kept_field(tr, False)
    kept = result.averaged_field(tr, kept)      # the result's voxel average, as finish does
    d = result.decide_length(decider, kept, False, anchored=anchor)
    held = np.asarray(decider.held_idx)
    return {"iterations": d["iterations"], "heldout_mse": d["heldout_mse"],
            "heldout_mse_start": d["curve"][0][1], "seconds": d["seconds"], "kept": kept,
            "decider": decider, "held": held, "start": result.field_volume(decider, kept),
            "fit": np.setdiff1d(np.arange(geo.n_views), held)}


def export_check(tr, case, d: dict, anchor: bool) -> dict:
    """The held-out residual of what the chosen form would export from the kept state."""
    from mi_grg.classical.pdhg import pdhg
    from mi_grg.training import result
    from mi_grg.training.distill import fit_to_volume
    geo = case.geometry
    t0 = time.perf_counter()
    kept, decider, fit, held = d["kept"], d["decider"], d["fit"], d["held"]
    b = (result.anchored_data(decider, kept, d["start"], fit) if anchor else case.train[fit])
    k = d["iterations"]
    grid = (pdhg(b, geo.with_angles(geo.angles[fit]), n_iter=k, lam=tr.cfg.protocol.refine_lam,
                 init=d["start"], progress=False) if k else d["start"])
    g, info = fit_to_volume(kept, geo, grid, lr=result._fit_rates(tr),
                            iterations=tr.cfg.protocol.fit_iterations, extent=tr.extent,
                            progress=False)
    p = result.projections(tr, g, held)
    return {"heldout_mse": float(np.mean(np.square(p - case.train[held], dtype=np.float64))),
            "fidelity_db": info["fidelity_db"], "seconds": time.perf_counter() - t0}


def pick(rec: dict) -> str:
    """The form ``refine_anchor="auto"`` takes: the lower held-out residual, ties anchored."""
    f = rec["forms"]
    return "anchored" if f["anchored"]["heldout_mse"] <= f["plain"]["heldout_mse"] else "plain"


def finish(tr, case) -> dict:
    """gr's result with the package's defaults from the trained state: the export's 3-D
    PSNR, the form taken and the seconds."""
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    t0 = time.perf_counter()
    vol, _, info = result.finish(tr, progress=False)
    ref = info.get("refine", {})
    return {"psnr": float(psnr_3d(vol, case.vol_gt)), "seconds": time.perf_counter() - t0,
            "anchor": ref.get("anchor"), "iterations": ref.get("iterations")}


def trained(name: str, n: int, data_root: Path, states: Path):
    """(the case, its set, its trained gr ``Trainer``, the training summary), resumed from
    ``states`` when trained before."""
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    case, which = make_case(name, n, data_root)
    out_dir = states / f"{name}_{n}"
    tr = Trainer(case, make_config("gr"), out_dir=out_dir, progress=False,
                 resume=(out_dir / "checkpoint.npz").exists())
    return case, which, tr, tr.run()


def run_case(name: str, n: int, data_root: Path, states: Path, with_finish: bool) -> dict:
    from mi_grg.classical.pdhg import PDHG
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    t0 = time.perf_counter()
    case, which, tr, summary = trained(name, n, data_root, states)
    geo = case.geometry

    def ps(v):
        return float(psnr_3d(v, case.vol_gt))
    field = result.averaged_field(tr, tr.field_gaussians())
    vol = result.field_volume(tr, field)
    rec = {"case": name, "set": which, "n": n, "n_gaussians": summary["n_gaussians"],
           "train_seconds": time.perf_counter() - t0, "gaussians": ps(tr.volume()),
           "voxel_averaged": ps(vol), "forms": {}}
    every = np.arange(geo.n_views)
    for form in ("anchored", "plain"):
        anchor = form == "anchored"
        d = decide(tr, case, anchor)
        b = result.anchored_data(tr, field, vol, every) if anchor else case.train
        sol = PDHG(b, geo, geo.angles, lam=tr.cfg.protocol.refine_lam, init=vol)
        at = {}
        for it in range(1, CONVERGED + 1):
            sol.step()
            if it in (d["iterations"], CONVERGED):
                at[it] = ps(_grid(sol.x, geo))
        rec["forms"][form] = {
            "iterations": d["iterations"], "heldout_mse": d["heldout_mse"],
            "heldout_mse_start": d["heldout_mse_start"], "decision_seconds": d["seconds"],
            "grid_at_chosen": at.get(d["iterations"], rec["voxel_averaged"]),
            "grid_converged": at[CONVERGED], "export_check": export_check(tr, case, d, anchor)}
    if with_finish:
        rec["finish"] = finish(tr, case)
    return rec


def markdown(records: dict) -> str:
    rows = ["| case | n | set | Gaussians alone / voxel-averaged | form | length chosen | "
            "held-out MSE of the grid (at 0) | held-out MSE of the export check | "
            "grid at the length | grid converged (400 it.) | export, defaults |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    gains = {}
    for which in ("tuning", "confirmation"):
        for r in (r for r in records.values() if r["set"] == which):
            chosen = pick(r)
            fin = r.get("finish")
            for form, f in r["forms"].items():
                mark = " (auto)" if form == chosen else ""
                export = (f"{fin['psnr']:.2f}" if fin and form == chosen else "")
                rows.append(
                    f"| {r['case']} | {r['n']} | {which} | {r['gaussians']:.2f} / "
                    f"{r['voxel_averaged']:.2f} | {form}{mark} | {f['iterations']} | "
                    f"{f['heldout_mse']:.4g} ({f['heldout_mse_start']:.4g}) | "
                    f"{f['export_check']['heldout_mse']:.4g} | {f['grid_at_chosen']:.2f} | "
                    f"{f['grid_converged']:.2f} | {export} |")
            gains.setdefault(which, []).append(
                r["forms"][chosen]["grid_at_chosen"] - r["forms"]["anchored"]["grid_at_chosen"])
    rows.append("")
    for which, g in gains.items():
        rows.append(f"Refined grid, auto − anchored, {which} ({len(g)} cases): mean "
                    f"{sum(g) / len(g):+.2f} dB ({', '.join(f'{x:+.2f}' for x in g)}).  ")
    return "\n".join(rows) + "\n"


def state_arguments(doc: str, out_name: str) -> argparse.ArgumentParser:
    """The options of a study on the trained states (cases, size, data, states, output)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["bone", "needles", "shepp"],
                    choices=list(CASES))
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--data", type=Path, default=Path("/tmp/field_result_data"))
    ap.add_argument("--states", type=Path, default=Path("/tmp/refine_anchor_states"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / out_name)
    return ap


def main():
    ap = state_arguments(__doc__, "refine_anchor")
    ap.add_argument("--finish", action="store_true",
                    help="also make gr's result with the package's defaults (the export)")
    ap.add_argument("--finish-only", action="store_true")
    ap.add_argument("--markdown-only", action="store_true")
    a = ap.parse_args()
    path = a.out.with_suffix(".json")
    if a.markdown_only:
        a.out.with_suffix(".md").write_text(markdown(json.loads(path.read_text())))
        return
    for name in a.cases:
        if a.finish_only:
            rec = json.loads(path.read_text())[f"{name}_{a.n}"]
            case, _, tr, _ = trained(name, a.n, a.data, a.states)
            rec["finish"] = finish(tr, case)
        else:
            rec = run_case(name, a.n, a.data, a.states, a.finish)
        save_record(a.out, f"{name}_{a.n}", rec, markdown)
        print(json.dumps({k: v for k, v in rec.items() if k != "forms"}),
              {k: (v["iterations"], round(v["grid_at_chosen"], 2)) for k, v in
               rec["forms"].items()}, flush=True)


if __name__ == "__main__":
    main()
