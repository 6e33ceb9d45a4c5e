"""The refinement's TV weight: is the fixed weight the right one, and can the run's own
held-out views choose it?

From one trained gr state per case (``refine_anchor.py --states``, resumed, not trained
again): the kept field (the state before the held-out views joined) voxelised, then for
each form of the refinement's data (anchored / plain, ``mi_grg.training.result``) and each
weight of ``LAMS``, PDHG on the fitted views from that start for ``CAP`` iterations. Every
``EVERY`` iterations: the held-out residual (what a rule may use) and the 3-D PSNR of the
grid (what says which choice was right). Iteration 0 is the start (no refinement).

Rules replayed on those curves, each picking (form, weight, length):

* ``default``: the package's rule when this study was made (weight ``refine_lam``, the
  form and length of lowest held-out residual, ties anchored; ``refine_tol`` came later:
  ``refine_tol.py`` replays it on these curves);
* ``heldout``: the lowest held-out residual over forms, weights and lengths;
* ``fall F``: the default's weight and form, the length where the held-out residual first
  completes the share F of its fall from the start to its minimum (``FALLS``; F = 1 is the
  default);
* ``none``: no refinement (the kept field's voxelisation);
* ``oracle``: the best 3-D PSNR on the curves (the ground truth's choice).

    MI_GRG_DATA=/work/shared/data python experiments/studies/refine_weight.py \\
        --cases bone needles shepp cement needles7 shells7 mni152 \\
        --states /tmp/refine_anchor_states --data /tmp/field_data [--finish 0.9]

``--finish F`` (with the curves recorded) makes gr's result from the same state with the
package's defaults but ``refine_fall=F`` and records its export's 3-D PSNR beside the
default's (``refine_anchor.py --finish``'s record, same state). Writes
docs/bench/refine_weight.json (merged per case) and .md.
"""
import json
import time

import numpy as np

from mi_grg.training.result import curve_length

from field_result import save_record
from refine_anchor import state_arguments, trained

LAMS = (0.001, 0.003, 0.01, 0.03)
FALLS = (0.99, 0.95, 0.9, 0.8)
CAP = 200
EVERY = 5


def curves(tr, case) -> dict:
    """{form: {lam: [(iteration, held-out MSE, 3-D PSNR)]}} from the kept field."""
    from mi_grg.classical.pdhg import PDHG
    from mi_grg.core.joseph import forward_project
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    geo = case.geometry
    kept, _, decider = result.kept_field(tr, False)
    kept = result.averaged_field(tr, kept)      # the result's voxel average, as finish does
    held = np.asarray(decider.held_idx)
    fit = np.setdiff1d(np.arange(geo.n_views), held)
    start = result.field_volume(decider, kept)
    out = {}
    for form in ("anchored", "plain"):
        if form == "anchored":
            b_fit = result.anchored_data(decider, kept, start, fit)
            b_held = result.anchored_data(decider, kept, start, held)
        else:
            b_fit, b_held = case.train[fit], case.train[held]

        def point(it, x):
            r = forward_project(x, geo, geo.angles[held]) - b_held
            return (it, float(np.mean(np.square(r, dtype=np.float64))),
                    float(psnr_3d(x, case.vol_gt)))
        out[form] = {}
        for lam in LAMS:
            solver = PDHG(b_fit, geo, geo.angles[fit], lam=lam, init=start)
            pts = [point(0, start)]
            for it in range(1, CAP + 1):
                solver.step()
                if it % EVERY == 0:
                    pts.append(point(it, np.asarray(solver.x.numpy(), np.float32)
                                     .reshape(geo.nVoxel)))
            out[form][str(lam)] = pts
    return out


def rules(rec: dict, default_lam: float) -> dict:
    """Each rule's (form, lam, iteration, 3-D PSNR)."""
    pts = [(form, float(lam), it, mse, ps) for form, by in rec["curves"].items()
           for lam, c in by.items() for it, mse, ps in c]
    order = {"anchored": 0, "plain": 1}

    def best(cands, key):
        f, lam, it, _, ps = min(cands, key=key)
        return {"form": f, "lam": lam, "iteration": it, "psnr": ps}
    by_mse = lambda p: (p[3], order[p[0]], p[2])  # noqa: E731
    default = best([p for p in pts if p[1] == default_lam], by_mse)
    out = {"default": default, "heldout": best(pts, by_mse)}
    curve = rec["curves"][default["form"]][str(default_lam)]
    for fall in FALLS:     # the package's own length rule, without its tolerance
        it, _ = curve_length([c[:2] for c in curve], fall, 0.0)
        ps = next(c[2] for c in curve if c[0] == it)
        out[f"fall {fall:g}"] = {**default, "iteration": it, "psnr": ps}
    out["none"] = best([p for p in pts if p[2] == 0], lambda p: 0)
    out["oracle"] = best(pts, lambda p: -p[4])
    return out


def finish_with_fall(tr, case, fall: float) -> dict:
    """gr's result from the trained state with ``refine_fall=fall`` (export's 3-D PSNR)."""
    from refine_anchor import finish
    tr.cfg.protocol.refine_fall = fall
    return finish(tr, case)


def markdown(records: dict) -> str:
    names = ("default", "heldout", *(f"fall {f:g}" for f in FALLS), "none", "oracle")
    rows = ["| case | set | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    diffs = {}
    for which in ("tuning", "confirmation"):
        for r in (r for r in records.values() if r["set"] == which):
            cells = []
            for k in names:
                x = r["rules"][k]
                cells.append(f"{x['psnr']:.2f} ({x['form'][0]}, {x['lam']:g}, {x['iteration']})")
            rows.append(f"| {r['case']} | {which} | " + " | ".join(cells) + " |")
            d = diffs.setdefault(which, {k: [] for k in names})
            for k in names:
                d[k].append(r["rules"][k]["psnr"] - r["rules"]["default"]["psnr"])
    rows += ["", "Cells: the grid's 3-D PSNR (dB) on the fitted views at the rule's choice "
             "(form a / p, weight, iteration; iteration 0: the start, no refinement).", ""]
    for which, d in diffs.items():
        rows.append(f"{which} ({len(d['default'])} cases), mean minus the default: "
                    + ", ".join(f"{k} {np.mean(v):+.2f} dB" for k, v in d.items()
                                if k != "default") + ".  ")
    fin = [r for r in records.values() if r.get("finish")]
    if fin:
        falls = sorted({f for r in fin for f in r["finish"]}, key=float)
        rows += ["", "gr's export (3-D PSNR, dB) from the same state: the defaults "
                 "(`refine_anchor.py --finish`) and `refine_fall=F`:", "",
                 "| case | set | defaults | " + " | ".join(f"fall {f}" for f in falls) + " |",
                 "|---|---|---|" + "---|" * len(falls)]
        gain = {}
        for which in ("tuning", "confirmation"):
            for r in (r for r in fin if r["set"] == which):
                base = r.get("default_export")
                cells = []
                for f in falls:
                    x = r["finish"].get(f)
                    cells.append("-" if x is None else f"{x['psnr']:.2f} ({x['iterations']} it.)"
                                 + ("" if base is None else f", {x['psnr'] - base:+.2f}"))
                    if x is not None and base is not None:
                        gain.setdefault((which, f), []).append(x["psnr"] - base)
                rows.append(f"| {r['case']} | {which} | "
                            + ("-" if base is None else f"{base:.2f}") + " | "
                            + " | ".join(cells) + " |")
        rows.append("")
        for (which, f), g in gain.items():
            rows.append(f"fall {f} − defaults, {which} ({len(g)} cases): mean "
                        f"{np.mean(g):+.2f} dB.  ")
    return "\n".join(rows) + "\n"


def main():
    from mi_grg.training.config import make_config
    ap = state_arguments(__doc__, "refine_weight")
    ap.add_argument("--replay-only", action="store_true",
                    help="replay the rules on the recorded curves, rewrite .json / .md")
    ap.add_argument("--finish", type=float, default=None, metavar="F",
                    help="gr's result with refine_fall=F from each case's state (curves "
                         "recorded before)")
    a = ap.parse_args()
    default_lam = float(make_config("gr").protocol.refine_lam)
    if a.replay_only:
        path = a.out.with_suffix(".json")
        records = json.loads(path.read_text())
        for rec in records.values():
            rec["rules"] = rules(rec, default_lam)
        path.write_text(json.dumps(records, indent=1))
        a.out.with_suffix(".md").write_text(markdown(records))
        return
    if a.finish is not None:
        anchor = json.loads((a.out.parent / "refine_anchor.json").read_text())
        for name in a.cases:
            key = f"{name}_{a.n}"
            rec = json.loads(a.out.with_suffix(".json").read_text())[key]
            case, _, tr, _ = trained(name, a.n, a.data, a.states)
            rec.setdefault("finish", {})[f"{a.finish:g}"] = finish_with_fall(tr, case, a.finish)
            rec["default_export"] = anchor.get(key, {}).get("finish", {}).get("psnr")
            save_record(a.out, key, rec, markdown)
            print(name, rec["finish"], flush=True)
        return
    for name in a.cases:
        t0 = time.perf_counter()
        case, which, tr, _ = trained(name, a.n, a.data, a.states)
        rec = {"case": name, "set": which, "n": a.n, "lams": list(LAMS), "cap": CAP,
               "curves": curves(tr, case)}
        rec["rules"] = rules(rec, default_lam)
        rec["seconds"] = time.perf_counter() - t0
        save_record(a.out, f"{name}_{a.n}", rec, markdown)
        print(name, json.dumps(rec["rules"]), f"{rec['seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
