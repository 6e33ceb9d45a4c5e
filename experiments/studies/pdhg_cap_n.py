"""PDHG's held-out cap at another grid size: ``--method pdhg`` (one-SE weight, held-out stop)
with its default cap of 60 iterations and with larger caps, on the cases of
``field_result.py`` at ``--n``.

At 128^3 the 60-iteration cap bound (docs/benchmarks.md, "PDHG's cap and weight rule"):
this asks what the same rule scores with a wider cap. The tuning cases chose the default
that grows with the grid (``mi_grg.classical.pdhg.heldout_cap``: 240 at 128^3); the
confirmation cases report it.

    MI_GRG_DATA=/work/shared/data python experiments/studies/pdhg_cap_n.py \\
        --cases needles needles7 shepp shells7 --n 128 --caps 60 240 --data /tmp/field_data
    MI_GRG_DATA=/work/shared/data python experiments/studies/pdhg_cap_n.py --cases shepp \\
        --n 128 --caps 240 --rules best morozov --cold 0.003 300 --data /tmp/field_data

Writes docs/bench/pdhg_cap_n.json (merged per case, size and cap) and .md.
"""
import argparse
import json
from pathlib import Path

from field_result import CASES, ROOT, make_case, pdhg_run, save_record


def run(name: str, n: int, cap: int, data_root: Path, rule: str = "one_se") -> dict:
    case, which = make_case(name, n, data_root)
    return {"case": name, "set": which, "n": n, "cap": cap, "rule": rule,
            **pdhg_run(case, n_iter=cap, lam_rule=rule)}


def cold(name: str, n: int, lam: float, iterations: int, data_root: Path) -> dict:
    """PDHG from zero at one weight for a fixed count (``stop="none"``), no decision."""
    case, which = make_case(name, n, data_root)
    return {"case": name, "set": which, "n": n, "cap": iterations, "rule": f"cold, lam {lam:g}",
            **pdhg_run(case, stop="none", n_iter=iterations, lam=lam), "lam": lam,
            "iterations": iterations}


def markdown(records: dict) -> str:
    rows = ["| case | n | set | rule | cap | 3-D PSNR (dB) | lam | iterations kept | s |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(records.values(), key=lambda r: (r["n"], r["case"], r.get("rule", "one_se"),
                                                     r["cap"])):
        rows.append(f"| {r['case']} | {r['n']} | {r['set']} | {r.get('rule', 'one_se')} | "
                    f"{r['cap']} | {r['psnr']:.2f} | {r['lam']:g} | {r['iterations']} | "
                    f"{r['seconds']:.0f} |")
    return "\n".join(rows) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["needles"], choices=list(CASES))
    ap.add_argument("--n", type=int, default=128)
    ap.add_argument("--caps", nargs="+", type=int, default=[60, 240])
    ap.add_argument("--rules", nargs="+", default=["one_se"],
                    help="PDHG's weight rules (lam_rule) to run at each cap")
    ap.add_argument("--cold", nargs=2, metavar=("LAM", "ITERATIONS"), default=None,
                    help="also PDHG from zero at LAM for ITERATIONS (no decision)")
    ap.add_argument("--data", type=Path, default=Path("/tmp/field_result_data"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "pdhg_cap_n")
    a = ap.parse_args()
    for name in a.cases:
        for rule in a.rules:
            for cap in a.caps:
                rec = run(name, a.n, cap, a.data, rule)
                suffix = "" if rule == "one_se" else f"_{rule}"
                save_record(a.out, f"{name}_{a.n}_{cap}{suffix}", rec, markdown)
                print(json.dumps(rec), flush=True)
        if a.cold is not None:
            lam, its = float(a.cold[0]), int(a.cold[1])
            rec = cold(name, a.n, lam, its, a.data)
            save_record(a.out, f"{name}_{a.n}_cold_{lam:g}_{its}", rec, markdown)
            print(json.dumps(rec), flush=True)

if __name__ == "__main__":
    main()
