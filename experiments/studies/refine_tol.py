"""The refinement's length within a tolerance of the held-out minimum (``refine_tol``).

The default refines to the held-out residual's minimum. Where that residual barely falls
(a smooth object the field already predicts), the minimum lies far along a flat curve and
the TV refinement's bias costs more than the views can see (mni152 at 64^3: the refined
grid 0.9 dB below the voxel-averaged field). ``refine_tol = t`` stops at the first check
within the share t of the minimum, and does not refine when the start is already there.

Three parts:

* ``--replay``: t chosen on the tuning cases' recorded curves (docs/bench/refine_weight.json:
  per case, form and weight the held-out residual and the grid's 3-D PSNR every 5
  iterations), the default's form and weight, each t of ``TOLS``; reported on both sets.
* ``--cases ... --tol T``: gr's export (the package's result steps) from each case's trained
  state, with ``refine_tol`` 0 (the default before it) and T: the 3-D PSNR of what the run
  exports.
* ``--runs KEY SET RUN_0 RUN_T``: the same comparison from two finished runs of one trained
  state (a 128^3 run and its result steps re-made with ``--resume --option refine_tol=T``).

    python experiments/studies/refine_tol.py --replay
    MI_GRG_DATA=/work/shared/data python experiments/studies/refine_tol.py \\
        --cases mni152 needles7 shells7 --tol 0.005 --states /tmp/tol_states --data /tmp/tol_data
    python experiments/studies/refine_tol.py --runs mni152_128 confirmation \\
        results/cpu128/table1/mni152/gr /tmp/mni128_tol

Writes docs/bench/refine_tol.json (merged per key) and .md.
"""
import json
import time
from pathlib import Path

import numpy as np

from field_result import ROOT, save_record
from refine_anchor import finish, state_arguments, trained

TOLS = (0.001, 0.002, 0.005, 0.01, 0.02)
CURVES = ROOT / "docs" / "bench" / "refine_weight.json"


def length_at(curve: list, tol: float) -> list:
    """[iteration, 3-D PSNR] of the check ``result.curve_length`` picks on a recorded curve
    [iteration, held-out MSE, 3-D PSNR] with refine_fall 1 and ``tol``."""
    from mi_grg.training.result import curve_length
    it, _ = curve_length(curve, 1.0, tol)
    return next([e[0], e[2]] for e in curve if e[0] == it)


def first_minimum(curve: list) -> list:
    """[iteration, 3-D PSNR] of the first check whose held-out MSE the next one does not
    undercut (a held-out rule tried against the tolerance), or the last check."""
    i = next((i for i in range(len(curve) - 1) if curve[i + 1][1] >= curve[i][1]),
             len(curve) - 1)
    return [curve[i][0], curve[i][2]]


def replay(curves: dict) -> dict:
    """{case key: {"set", "default": [it, psnr], "tol": {t: [it, psnr]}, "first_min",
    "oracle": [it, psnr]}} on the default's form and weight (the oracle: the best 3-D PSNR
    along the curve, picked with the ground truth)."""
    out = {}
    for key, r in curves.items():
        d = r["rules"]["default"]
        c = r["curves"][d["form"]][f"{d['lam']:g}"]
        best = max(c, key=lambda e: e[2])
        out[key] = {"set": r["set"], "form": d["form"],
                    "default": [d["iteration"], d["psnr"]],
                    "tol": {f"{t:g}": length_at(c, t) for t in TOLS},
                    "first_min": first_minimum(c), "oracle": [best[0], best[2]]}
    return out


def markdown(records: dict) -> str:
    rows = []
    rep = records.get("replay")
    if rep:
        rows += ["Replayed on the recorded curves (grid on the fitted views, 3-D PSNR dB; "
                 "cells: the length, the change against the default):", "",
                 "| case | set | default | " + " | ".join(f"tol {t:g}" for t in TOLS)
                 + " | first minimum | oracle |", "|---|---|---|" + "---|" * (len(TOLS) + 2)]
        gain = {}
        for which in ("tuning", "confirmation"):
            for key, r in rep.items():
                if r["set"] != which:
                    continue
                it0, p0 = r["default"]
                cells = []
                for t in TOLS:
                    it, p = r["tol"][f"{t:g}"]
                    cells.append(f"{it} ({p - p0:+.2f})")
                    gain.setdefault((which, t), []).append(p - p0)
                for name in ("first_min", "oracle"):
                    if name in r:
                        it, p = r[name]
                        cells.append(f"{it} ({p - p0:+.2f})")
                        gain.setdefault((which, name), []).append(p - p0)
                rows.append(f"| {key} | {which} | {it0} it., {p0:.2f} | " + " | ".join(cells)
                            + " |")
        rows.append("")
        for which in ("tuning", "confirmation"):
            rows.append(f"{which}, mean change: " + ", ".join(
                f"{t if isinstance(t, str) else f'tol {t:g}'} "
                f"{np.mean(gain[(which, t)]):+.3f} dB" for t in (*TOLS, "first_min", "oracle")
                if (which, t) in gain) + ".  ")
    fin = {k: v for k, v in records.items() if k != "replay"}
    if fin:
        rows += ["", "gr's export from the same trained state (3-D PSNR dB; refinement "
                 "iterations, form):", "",
                 "| case | set | refine_tol 0 (the earlier default) | refine_tol T | change |", "|---|---|---|---|---|"]
        gain = {}
        for key, r in fin.items():
            d, t = r["default"], r["tol"]
            rows.append(f"| {key} | {r['set']} | {d['psnr']:.2f} ({d['iterations']}, "
                        f"{d['form']}) | {t['psnr']:.2f} ({t['iterations']}, {t['form']}; "
                        f"tol {r['refine_tol']:g}) | {t['psnr'] - d['psnr']:+.2f} |")
            gain.setdefault(r["set"], []).append(t["psnr"] - d["psnr"])
        rows.append("")
        for which, g in gain.items():
            rows.append(f"{which} ({len(g)} cases): mean {np.mean(g):+.2f} dB.  ")
    return "\n".join(rows) + "\n"


def _export(name: str, n: int, data: Path, states: Path, tol: float) -> dict:
    case, which, tr, _ = trained(name, n, data, states)
    tr.cfg.protocol.refine_tol = tol
    r = finish(tr, case)
    a = r.get("anchor") or {}
    return which, {"psnr": r["psnr"], "iterations": r["iterations"], "seconds": r["seconds"],
                   "form": "anchored" if a.get("anchored") else "plain"}


def _from_run(run: Path) -> dict:
    m = json.loads((Path(run) / "metrics.json").read_text())
    r = m["method_info"]["refine"]
    return {"psnr": m["psnr_3d"], "iterations": r["iterations"],
            "seconds": r["decision_seconds"] + r.get("final_seconds", 0.0)
            + (r.get("fit") or {}).get("seconds", 0.0),
            "form": "anchored" if r["anchor"]["anchored"] else "plain",
            "refine_tol": r.get("tol", 0.0), "code": m["machine"]["mi_grg"]}


def main():
    ap = state_arguments(__doc__, "refine_tol")
    ap.add_argument("--replay", action="store_true",
                    help="replay TOLS on docs/bench/refine_weight.json's curves")
    ap.add_argument("--tol", type=float, default=0.005)
    ap.add_argument("--runs", nargs=4, metavar=("KEY", "SET", "RUN_0", "RUN_T"))
    a = ap.parse_args()
    if a.runs:
        key, which, run0, run_t = a.runs
        default, tol = _from_run(Path(run0)), _from_run(Path(run_t))
        if default["refine_tol"] != 0.0 or tol["refine_tol"] <= 0.0:
            ap.error("RUN_0 must be made with refine_tol 0 and RUN_T with refine_tol > 0")
        save_record(a.out, key, {"set": which, "refine_tol": tol["refine_tol"],
                                 "default": default, "tol": tol}, markdown)
        print(a.out.with_suffix(".md").read_text())
        return
    if a.replay:
        save_record(a.out, "replay", replay(json.loads(CURVES.read_text())), markdown)
        print(a.out.with_suffix(".md").read_text())
        return
    for name in a.cases:
        t0 = time.perf_counter()
        which, default = _export(name, a.n, a.data, a.states, 0.0)
        _, tol = _export(name, a.n, a.data, a.states, a.tol)
        rec = {"set": which, "refine_tol": a.tol, "default": default, "tol": tol,
               "seconds": time.perf_counter() - t0}
        save_record(a.out, f"{name}_{a.n}", rec, markdown)
        print(name, json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
