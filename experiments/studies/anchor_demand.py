"""The refinement's anchor against densification's demand: which form each case's export
prefers, what the held-out views chose, and what ``mi_grg.training.densify.demand`` says.

Usage:  .venv/bin/python experiments/studies/anchor_demand.py --runs CASE:SET:DIR ...
            [--report docs/bench/anchor_demand.md] [--add]

``--add`` keeps the rows already in the report's .json (run folders of earlier sessions,
which need not exist any more) and adds or replaces the rows of ``--runs``.

Each DIR is a finished gr run (metrics.json, train_log.csv), where it was made beside DIR_on
and DIR_off: the same trained state with its result's steps redone anchored and plain
(``mi-grg reconstruct DATA --method gr --out DIR_on --resume --option refine_anchor=on`` on
a copy of DIR without its metrics.json; likewise off). A form neither beside DIR nor taken
by DIR has no export in the table. SET names the case's role (tuning, confirmation, ...).
For each case: the densification verdict from the run's own log and window, the held-out
minima of the two forms (the rule before this study took the lower one: "held-out"), the
exports of both forms, and what today's ``refine_anchor="auto"`` takes. Research only: the
ground truth enters no choice.
"""
from __future__ import annotations

import argparse
import csv
import json
import re
from pathlib import Path

from mi_grg.training.densify import DensifyWindow, demand


def one(case: str, role: str, run: Path) -> dict:
    m = json.loads((run / "metrics.json").read_text())
    info = m["method_info"]
    s = info["schedule"]
    window = DensifyWindow(s["densify_start"], s["densify_stop"], s["densify_interval"],
                           info["max_gaussians"])
    with open(run / "train_log.csv") as f:
        log = [{"iteration": int(r["iteration"]), "n_gaussians": int(float(r["n_gaussians"]))}
               for r in csv.DictReader(f) if r.get("n_gaussians")]
    base = info["refine"]["anchor"]
    forms = {}
    for form, suffix in (("anchored", "_on"), ("plain", "_off")):
        other = run.parent / (run.name + suffix) / "metrics.json"
        if other.is_file():
            mf = json.loads(other.read_text())
        elif base["anchored"] == (form == "anchored"):
            mf = m                          # the run itself took this form
        else:
            mf = None                       # not run: its export is not known
        mse = base["heldout_mse"].get(form)
        if mse is None and mf is not None:
            mse = mf["method_info"]["refine"]["anchor"]["heldout_mse"][form]
        forms[form] = {"heldout_mse": mse,
                       "psnr_3d": None if mf is None else mf["psnr_3d"]}
    verdict = demand(log, window)
    heldout = min(forms, key=lambda f: (forms[f]["heldout_mse"], f != "anchored"))
    auto = heldout if verdict["met"] else "plain"
    pa, pp = forms["anchored"]["psnr_3d"], forms["plain"]["psnr_3d"]
    return {"case": case, "set": role, "run": str(run), "n": int(info["n_gaussians"]),
            "nVoxel": m["nVoxel"], "demand": verdict, "forms": forms,
            "heldout_takes": heldout, "auto_takes": auto,
            "gain": 0.0 if auto == heldout else forms[auto]["psnr_3d"] - forms[heldout]["psnr_3d"],
            "plain_minus_anchored": None if None in (pa, pp) else pp - pa}


def _db(x) -> str:
    return "" if x is None else f"{x:.2f}"


def report(rows: list, path: Path, commands: list) -> None:
    made = ", then ".join(f"`{c}`" for c in commands)
    lines = ["# The refinement's anchor against densification's demand", "",
             f"Made by {made} (experiments/studies/anchor_demand.py) from run folders "
             "(how they were made: docs/benchmarks.md, \"The refinement's "
             "anchor\"; each row's numbers are in the .json beside this file). 3-D PSNR of "
             "each form's export in dB; held-out: the lower held-out minimum of the two "
             "forms (the rule before); auto: today's `refine_anchor=\"auto\"`.", "",
             "| case | set | n | Gaussians (share of the cap) | growth, last quarter | demand | "
             "held-out MSE anchored / plain | held-out takes | anchored | plain | auto takes "
             "| auto − held-out |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d, f = r["demand"], r["forms"]
        lines.append(
            f"| {r['case']} | {r['set']} | {r['nVoxel'][0]} | {r['n']} "
            f"({d['cap_share']:.3f}) | {100 * d['growth']:+.2f} % | "
            f"{'met' if d['met'] else '**not met**'} | {f['anchored']['heldout_mse']:.4g} / "
            f"{f['plain']['heldout_mse']:.4g} | {r['heldout_takes']} | "
            f"{_db(f['anchored']['psnr_3d'])} | {_db(f['plain']['psnr_3d'])} | "
            f"{r['auto_takes']} | {r['gain']:+.2f} |")
    for role in sorted({r["set"] for r in rows}):
        g = [r["gain"] for r in rows if r["set"] == role]
        lines.append(f"\n{role}: auto − held-out {sum(g) / len(g):+.2f} dB on average over "
                     f"{len(g)} case(s), lowest {min(g):+.2f}.")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    path.with_suffix(".json").write_text(json.dumps(rows, indent=1))


def main(argv=None) -> int:
    import sys
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", nargs="+", required=True, help="CASE:SET:DIR")
    p.add_argument("--report", type=Path, default=Path("docs/bench/anchor_demand.md"))
    p.add_argument("--add", action="store_true",
                   help="keep the rows of the report's .json and add these")
    a = p.parse_args(argv)
    new = []
    for spec in a.runs:
        case, role, run = spec.split(":", 2)
        new.append(one(case, role, Path(run)))
    command = "python experiments/studies/anchor_demand.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    rows, commands = new, [command]
    if a.add and a.report.with_suffix(".json").is_file():
        ident = lambda r: (r["case"], r["set"], r["nVoxel"][0])  # noqa: E731
        kept = json.loads(a.report.with_suffix(".json").read_text())
        mine = {ident(r) for r in new}
        rows = [r for r in kept if ident(r) not in mine] + new
        # the commands that made the kept rows, as the report before named them
        head = a.report.read_text().split(" (experiments/studies/anchor_demand.py)")[0]
        found = re.findall(r"`(python experiments/studies/anchor_demand\.py[^`]*)`", head)
        commands = list(dict.fromkeys(found + commands))
    report(rows, a.report, commands)
    print(f"wrote {a.report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
