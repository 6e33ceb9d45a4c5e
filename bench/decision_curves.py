"""The refinement's length decision, both forms' held-out curves, and early stopping replayed.

Usage:  .venv/bin/python bench/decision_curves.py --out results/cpu --cases shepp needles
            [--patience 4 6 8 10] [--report docs/bench/decision_curves.md]

For each finished gr run of a runner's folder (``OUT/table1/<case>/gr``, with its checkpoint
and metrics.json), the trained state is restored and the refinement's length is decided
again for both forms (anchored and plain data; ``mi_grg.training.result.decide_length``),
each to the cap, so that both held-out curves are on record (runs made before metrics.json
kept them hold only the chosen form's). The decision re-made must be the run's (form and
length; a check that it was re-made as it was). Then a patience rule is replayed on both
curves: each form's decision stops once its curve has set no new minimum for P checks; the
record says whether the form and the length it picks differ from the full decision's, and
how many PDHG iterations it saves.
Decides nothing by itself: the ground truth enters nothing here.
"""
from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import mi_grg  # noqa: F401  (selects the variant)


def with_patience(curve: list, patience: int) -> tuple:
    """(the curve's minimum, its iteration, the last iteration run) when the decision
    stops as ``mi_grg.training.result.past_patience`` says (0: the whole curve)."""
    from mi_grg.training.result import past_patience
    stop = next((i for i in range(1, len(curve)) if past_patience(curve[:i + 1], patience)),
                len(curve) - 1)
    best = min(curve[:stop + 1], key=lambda c: c[1])
    return best[1], best[0], curve[stop][0]


def decide_again(out: Path, case_name: str) -> dict:
    """Both forms' curves for one finished run (module docstring)."""
    from mi_grg.data.dataset import load_case
    from mi_grg.training.config import make_config
    from mi_grg.training.result import (averaged_field, decide_length, field_volume,
                                        kept_field)
    from mi_grg.training.trainer import Trainer
    run_dir = out / "table1" / case_name / "gr"
    spec = json.loads((run_dir / "run_spec.json").read_text())
    refine = json.loads((run_dir / "metrics.json").read_text())["method_info"]["refine"]
    case = load_case(out / "data" / case_name)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(case, make_config("gr", None, **spec["options"]), out_dir=tmp,
                          progress=False, resume=run_dir / "checkpoint.npz")
        trainer.run()
        kept, _, decider = kept_field(trainer, progress=False)
        kept = averaged_field(trainer, kept)    # the result's voxel average, as finish does
        start = field_volume(decider, kept)
        forms = {}
        for name, anchored in (("anchored", True), ("plain", False)):
            d = decide_length(decider, kept, progress=False, anchored=anchored, start=start,
                              patience=0)
            forms[name] = {"curve": d["curve"], "iterations": d["iterations"],
                           "seconds": d["seconds"]}
            print(f"  {case_name} {name}: length {d['iterations']}, {d['seconds']:.1f} s",
                  flush=True)
    chosen = min(forms, key=lambda f: min(m for _, m in forms[f]["curve"]))
    recorded = "anchored" if refine["anchor"]["anchored"] else "plain"
    return {"case": case_name, "n": case.geometry.nVoxel[0], "forms": forms,
            "recorded": {"form": recorded, "iterations": refine["iterations"]},
            "remade": {"form": chosen, "iterations": forms[chosen]["iterations"]}}


def replay(rec: dict, patience: int) -> dict:
    """The patience rule's decision on ``rec``'s two curves against the full decision."""
    cut = {f: with_patience(x["curve"], patience) for f, x in rec["forms"].items()}
    form = min(cut, key=lambda f: cut[f][0])       # ties keep "anchored" (listed first)
    ran = sum(c[2] for c in cut.values())
    full = sum(x["curve"][-1][0] for x in rec["forms"].values())
    return {"form": form, "iterations": cut[form][1], "iterations_run": ran,
            "saved": full - ran,
            "same": form == rec["remade"]["form"] and cut[form][1] == rec["remade"]["iterations"]}


def report(records: list, patiences: list, path: Path) -> None:
    from mi_grg.methods import machine_info
    lines = ["# The refinement's length decision with a patience rule "
             "(`bench/decision_curves.py`)", "",
             f"Code {machine_info()['mi_grg']}, {platform.machine()}; each case's decision re-made "
             "from its run's checkpoint for both forms, to the cap; the rule replayed on "
             "both curves. Same: the form and length equal the full decision's.", "",
             "| case | n | full decision (form, length) | re-made as recorded | " +
             " | ".join(f"P={p}: same / iterations saved" for p in patiences) + " |",
             "|---|---|---|---|" + "---|" * len(patiences)]
    for r in records:
        cells = [f"{'yes' if (x := replay(r, p))['same'] else '**no**'} / {x['saved']}"
                 for p in patiences]
        lines.append(f"| {r['case']} | {r['n']} | {r['remade']['form']}, "
                     f"{r['remade']['iterations']} | "
                     f"{'yes' if r['remade'] == r['recorded'] else '**no**'} | "
                     + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="a runner's results folder")
    ap.add_argument("--cases", nargs="+", required=True)
    ap.add_argument("--patience", type=int, nargs="+", default=[4, 6, 8, 10])
    ap.add_argument("--report", type=Path, default=Path("docs/bench/decision_curves.md"))
    args = ap.parse_args()
    if any(p < 1 for p in args.patience):
        ap.error("--patience values must be >= 1")
    json_path = args.report.with_suffix(".json")
    records = json.loads(json_path.read_text()) if json_path.exists() else []
    for name in args.cases:
        t0 = time.perf_counter()
        rec = decide_again(args.out, name)
        rec["seconds"] = time.perf_counter() - t0
        records = [r for r in records if (r["case"], r["n"]) != (rec["case"], rec["n"])]
        records.append(rec)
        json_path.write_text(json.dumps(records, indent=1))   # kept after every case
        report(records, args.patience, args.report)
    print(f"wrote {args.report} and {json_path}")


if __name__ == "__main__":
    main()
