"""gr's training loss against TV's prior: a stronger TV, a least-squares data term, no D-SSIM.

The Gaussians alone trail a converged TV on the piecewise-constant cases (blobs, needles):
the result's steps carry gr there. Does the training loss close that gap? One gr run per
(case, variant) on Table 1's case data (``mi-grg experiment table1`` writes it), scored by
the parts every run records (``method_info.result.parts``: the trained Gaussians alone,
voxel-averaged, the refined grid, the export) and by its held-out PSNR (what a rule choosing
the variant could use). ``default`` is Table 1's own gr run of the case.

    .venv/bin/python experiments/studies/training_loss.py --table1 results/cpu \\
        --runs /tmp/training_loss --cases needles shepp bone blobs shells cement mni152 \\
        shell shepp-parallel --variants rms_ssim0 l1_ssim0

A run folder that holds a metrics.json is read, not run again. Writes
docs/bench/training_loss.json (merged per case and variant) and .md.
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "bench" / "training_loss"
TUNING = ("bone", "needles", "shepp")
#: variant: gr options (``--option key=value``)
VARIANTS = {
    "tv0.2": {"lambda_tv": 0.2},
    "tv0.8": {"lambda_tv": 0.8},
    "rms": {"data_loss": "rms"},
    "rms_ssim0": {"data_loss": "rms", "lambda_ssim": 0.0},
    "l1_ssim0": {"lambda_ssim": 0.0},
}


def record(metrics: Path) -> dict:
    m = json.loads(metrics.read_text())
    mi = m["method_info"]
    return {"parts": mi["result"]["parts"], "best_heldout_psnr": mi["best_heldout_psnr"],
            "n_gaussians": mi["n_gaussians"], "seconds": m["seconds"],
            "refine_iterations": mi["refine"].get("iterations"),
            "options": m.get("options") or {}, "machine": m.get("machine")}


def run(case_dir: Path, out: Path, options: dict) -> Path:
    if not (out / "metrics.json").exists():
        cmd = [sys.executable, "-m", "mi_grg.cli", "reconstruct", str(case_dir),
               "--method", "gr", "--out", str(out)]
        for k, v in options.items():
            cmd += ["--option", f"{k}={v}"]
        subprocess.run(cmd, check=True)
    return out / "metrics.json"


def markdown(records: dict) -> str:
    variants = sorted({v for rec in records.values() for v in rec if v != "default"})
    lines = ["# gr's training loss (`experiments/studies/training_loss.py`)", "",
             "One gr run per case and variant, 64^3, 25 noisy views, Table 1's data; 3-D "
             "PSNR (dB) of the trained Gaussians alone / the export (vol_pred), and the "
             "variant's difference from the default (Table 1's gr run). Held-out: the run's "
             "best held-out PSNR minus the default's (what a rule could choose by).", ""]
    for v in variants:
        opts = " ".join(f"--option {k}={x}" for k, x in VARIANTS.get(v, {}).items())
        lines += [f"## {v}: `{opts}`", "",
                  "| case | set | Gaussians | export | Gaussians − default | export − default "
                  "| held-out − default | time (s) |", "|---|---|---|---|---|---|---|---|"]
        sums = {}
        for case in sorted(records, key=lambda c: (c not in TUNING, c)):
            rec = records[case]
            if v not in rec or "default" not in rec:
                continue
            a, d = rec[v], rec["default"]
            dg = a["parts"]["gaussians"] - d["parts"]["gaussians"]
            de = a["parts"]["export"] - d["parts"]["export"]
            dh = a["best_heldout_psnr"] - d["best_heldout_psnr"]
            which = "tuning" if case in TUNING else "confirmation"
            sums.setdefault(which, []).append((dg, de))
            lines.append(f"| {case} | {which} | {a['parts']['gaussians']:.2f} | "
                         f"{a['parts']['export']:.2f} | {dg:+.2f} | {de:+.2f} | {dh:+.2f} | "
                         f"{a['seconds']:.0f} |")
        for which, xs in sums.items():
            lines.append(f"| mean, {which} ({len(xs)}) | | | | "
                         f"{sum(x[0] for x in xs) / len(xs):+.2f} | "
                         f"{sum(x[1] for x in xs) / len(xs):+.2f} | | |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--table1", type=Path, required=True,
                    help="a table1 results folder (its data/ and table1/<case>/gr/)")
    ap.add_argument("--runs", type=Path, required=True, help="where the variants' runs go")
    ap.add_argument("--cases", nargs="+", required=True)
    ap.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), required=True)
    args = ap.parse_args(argv)
    path = OUT.with_suffix(".json")
    records = json.loads(path.read_text()) if path.exists() else {}
    for case in args.cases:
        rec = records.setdefault(case, {})
        rec["default"] = record(args.table1 / "table1" / case / "gr" / "metrics.json")
        for v in args.variants:
            metrics = run(args.table1 / "data" / case, args.runs / f"{case}_{v}", VARIANTS[v])
            rec[v] = record(metrics)
            path.write_text(json.dumps(records, indent=1))
            OUT.with_suffix(".md").write_text(markdown(records))


if __name__ == "__main__":
    main()
