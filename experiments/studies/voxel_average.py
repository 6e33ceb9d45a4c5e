"""The voxel average's strength: what the recorded gr runs' own views say about it.

The result's first step (mi_grg.training.result) blurs the trained field by a share f of a
voxel's box variance (``voxel_average``: 0.75, chosen at 64^3 on the tuning cases, until
this study chose 0.5). At 128^3 0.75 cost shepp-parallel 0.19 dB. For each recorded run
(its checkpoint, resumed, nothing trained again): the 3-D PSNR of the field's
voxelisation at each f (research record, the ground truth), and the held-out residual of
the state kept before the held-out views joined training, blurred by the same f and
projected exactly onto those views (what a rule may use). A rule is worth adopting only
where the residual's minimum falls near the PSNR's maximum on the tuning cases and on the
confirmation cases.

    MI_GRG_DATA=/work/shared/data python experiments/studies/voxel_average.py \\
        --runs results/cpu/table1 results/cpu128/table1 \\
        --finish "0.75 fixed" "0.5 fixed" "0.5 + held-out"

``--finish`` also replays the whole result (``result.finish``) under those settings
(``VARIANTS``).

Writes docs/bench/voxel_average.json (merged per run) and .md.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "bench" / "voxel_average"
SHARES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0)
TUNING = ("bone", "needles", "shepp")


def load_trainer(run_dir: Path):
    """(case, the run's resumed ``Trainer``) of a finished gr run folder."""
    from mi_grg.lab.runner import suite_case
    from mi_grg.lab.suite import CaseSpec
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    spec = json.loads((run_dir / "run_spec.json").read_text())
    fields = {k: v for k, v in spec["case"].items() if k in CaseSpec.__dataclass_fields__}
    case = suite_case(CaseSpec(**fields), run_dir.parents[2] / "data")
    tr = Trainer(case, make_config("gr", **spec["options"]), progress=False,
                 resume=run_dir / "checkpoint.npz")
    tr.run()
    return case, tr


def study(run_dir: Path) -> dict:
    from mi_grg.core.voxel_average import convolve_gaussians, voxel_variance
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    t0 = time.perf_counter()
    case, tr = load_trainer(run_dir)
    geo = case.geometry
    st = tr.state
    final = tr.field_gaussians()
    kept = tr.field_gaussians(st.kept_raw, st.kept_density_scale)
    held = np.asarray(tr.held_idx)
    box = voxel_variance(geo, 1.0)
    rows = []
    for f in SHARES:
        g = convolve_gaussians(final, f * box)
        k = convolve_gaussians(kept, f * box)
        res = result.projections(tr, k, held) - case.train[held]
        rows.append({"share": f, "psnr": float(psnr_3d(result.field_volume(tr, g),
                                                       case.vol_gt)),
                     "heldout_mse": float(np.mean(res.astype(np.float64) ** 2))})
    name = run_dir.parent.name
    return {"case": name, "n": int(geo.nVoxel[0]),
            "set": "tuning" if name in TUNING else "confirmation",
            "n_gaussians": len(final), "held_out_views": held.tolist(), "rows": rows,
            "seconds": time.perf_counter() - t0}


#: The result's settings replayed by ``--finish``: name -> (voxel_average, field_blur).
VARIANTS = {"0.75 fixed": (0.75, "none"), "0.5 fixed": (0.5, "none"),
            "0.5 + held-out": (0.5, "heldout"), "0.25 fixed": (0.25, "none"),
            "0.75 + held-out": (0.75, "heldout")}


def finish_variants(run_dir: Path, names) -> dict:
    """The whole result (``result.finish``) of the run's trained state under each of
    ``VARIANTS``' settings ``names``: its parts' 3-D PSNRs and the share it used."""
    import dataclasses
    from mi_grg.training import result
    case, tr = load_trainer(run_dir)
    protocol = tr.cfg.protocol
    out = {}
    for name in names:
        f, blur = VARIANTS[name]
        tr.cfg = dataclasses.replace(tr.cfg, protocol=dataclasses.replace(
            protocol, voxel_average=f, field_blur=blur))
        t0 = time.perf_counter()
        _, _, info = result.finish(tr, progress=False)
        out[name] = {"parts": info["parts"], "share": info["voxel_average"]["share"],
                     "refine_iterations": (info.get("refine") or {}).get("iterations"),
                     "seconds": time.perf_counter() - t0}
        print(f"  {run_dir.parent.name} {name}: share {out[name]['share']:g}, "
              f"{info['parts']}", file=sys.stderr, flush=True)
    tr.cfg = dataclasses.replace(tr.cfg, protocol=protocol)
    return out


def markdown(records: dict) -> str:
    lines = ["# The voxel average's strength on the recorded gr runs",
             "", "Made by `experiments/studies/voxel_average.py` from each run's checkpoint "
             "(nothing trained again). PSNR: the field's voxelisation blurred by f of a "
             "voxel's box variance (ground truth, research record). Held-out: the mean "
             "squared residual of the kept state, blurred by the same f, on the held-out "
             "views, relative to f = 0 (what a rule may use).", "",
             "| case | n | set | " + " | ".join(f"f={f:g}" for f in SHARES)
             + " | best f (PSNR) | best f (held-out) |",
             "|---|---|---|" + "---|" * len(SHARES) + "---|---|"]
    for key in sorted(records, key=lambda k: (records[k]["n"], records[k]["set"], k)):
        r = records[key]
        rows = r["rows"]
        base = rows[0]["heldout_mse"]
        cells = [f"{x['psnr']:.2f} ({100 * (x['heldout_mse'] / base - 1):+.2f}%)"
                 for x in rows]
        bp = max(rows, key=lambda x: x["psnr"])["share"]
        bh = min(rows, key=lambda x: x["heldout_mse"])["share"]
        lines.append(f"| {r['case']} | {r['n']} | {r['set']} | " + " | ".join(cells)
                     + f" | {bp:g} | {bh:g} |")
    done = [k for k in records if records[k].get("finish")]
    if done:
        names = [n for n in VARIANTS if any(n in records[k]["finish"] for k in done)]
        lines += ["", "## The whole result under each setting (`--finish`)", "",
                  "3-D PSNR of vol_pred (the exported field's voxelisation) after every "
                  "result step (voxel average, TV refinement, fit back), from the same "
                  "trained state; in brackets the share used and the refinement's length.",
                  "", "| case | n | set | " + " | ".join(names) + " |",
                  "|---|---|---|" + "---|" * len(names)]
        sums = {}
        for key in sorted(done, key=lambda k: (records[k]["n"], records[k]["set"], k)):
            r, fin = records[key], records[key]["finish"]
            cells = []
            for n in names:
                x = fin.get(n)
                if x is None:
                    cells.append("")
                    continue
                cells.append(f"{x['parts']['export']:.2f} ({x['share']:g}, "
                             f"{x['refine_iterations']})")
                sums.setdefault((r["n"], r["set"], n), []).append(x["parts"]["export"])
            lines.append(f"| {r['case']} | {r['n']} | {r['set']} | " + " | ".join(cells)
                         + " |")
        notes = sorted({f"{k} {n}: {x['from']}" for k in done
                        for n, x in records[k]["finish"].items() if x.get("from")})
        lines += [""] + [f"- {t}" for t in notes] if notes else []
        lines += ["", "| mean over | " + " | ".join(names) + " |",
                  "|---|" + "---|" * len(names)]
        for n_, which in sorted({(k[0], k[1]) for k in sums}):
            cells = [f"{np.mean(sums[(n_, which, n)]):.2f} ({len(sums[(n_, which, n)])})"
                     if (n_, which, n) in sums else "" for n in names]
            lines.append(f"| {n_}^3 {which} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="+", type=Path, required=True,
                    help="experiment folders holding <case>/gr run folders")
    ap.add_argument("--cases", nargs="*", help="only these cases")
    ap.add_argument("--finish", nargs="*", choices=list(VARIANTS),
                    help="also replay the whole result under these settings")
    a = ap.parse_args()
    import mi_grg  # noqa: F401  (sets the variant)
    path = OUT.with_suffix(".json")
    records = json.loads(path.read_text()) if path.exists() else {}
    for root in a.runs:
        for run_dir in sorted(root.glob("*/gr")):
            if a.cases and run_dir.parent.name not in a.cases:
                continue
            if not (run_dir / "checkpoint.npz").exists():
                continue
            rec = study(run_dir)
            key = f"{rec['case']}_{rec['n']}"
            rec["finish"] = (records.get(key) or {}).get("finish", {})
            if a.finish:
                rec["finish"].update(finish_variants(run_dir, a.finish))
            # re-read first: another process may have written cases of its own
            records = json.loads(path.read_text()) if path.exists() else {}
            records[key] = rec
            path.write_text(json.dumps(records, indent=1))
            OUT.with_suffix(".md").write_text(markdown(records))
            print(f"{rec['case']} {rec['n']}: " + ", ".join(
                f"{x['share']:g}: {x['psnr']:.2f} dB / {x['heldout_mse']:.4g}"
                for x in rec["rows"]), f"({rec['seconds']:.0f} s)", file=sys.stderr,
                flush=True)


if __name__ == "__main__":
    main()
