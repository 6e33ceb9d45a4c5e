"""Reconstruction quality and speed: fdk, sart, asd-pocs, pdhg, r2 and gr on the phantom suite.

Each (phantom, size, method) runs in its own process, so that its peak resident memory
(ru_maxrss) is its own. Cases: 25 noisy views (TIGRE CTnoise, I0 1e4, electronic std 10),
default scanner (mi_grg.data.simulate.default_geometry), detector 1.5 x the volume size.
Writes docs/bench/reconstruct.json and .md (medians are not taken here: one run per cell,
the training runs take minutes; the seed is fixed).

    python bench/reconstruct.py                   # 64^3, phantoms shepp, needles, shells
    python bench/reconstruct.py --sizes 64 128    # also 128^3 (about an hour more)
    python bench/reconstruct.py --sizes 128 --phantoms shepp --methods gr
    python bench/reconstruct.py --methods gr --option extent=4.5 --option iterations=1500
    python bench/reconstruct.py --sizes 128 --methods gr --logs out/cells   # keep the runs

``--logs DIR`` keeps each cell's run files (train_log.csv with the 3-D PSNR and held-out
PSNR at every evaluation, metrics.json, the volume) in DIR/<phantom>_<n>_<method>[_options].

``--option KEY=VALUE`` goes to r2 and gr (TrainConfig fields, as ``mi-grg reconstruct
--option``); such cells are kept apart from the default ones (their options are part of
the cell). ``MI_GRG_VARIANT=cuda_ad_mono`` runs the cells on a GPU.

The cells measured replace the same (phantom, size, method) cells of an existing
reconstruct.json, the others are kept (each row records its date and code version);
``--fresh`` starts a new file.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("fdk", "sart", "asd-pocs", "pdhg", "r2", "gr")


def one(phantom: str, n: int, method: str, options: dict, logs: str | None = None) -> dict:
    """Simulate (seeded) and reconstruct one case in this process; ``options`` (strings,
    TrainConfig fields) go to r2 and gr only; ``logs``: a folder that keeps the run's files
    (train_log.csv with the 3-D PSNR at every evaluation, metrics.json) per cell."""
    import mi_grg
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=n, det=int(1.5 * n), views=25)
    case = simulate_case(phantom, geo, default_test_angles(25), NoiseModel(), seed=0)
    opts = {} if method == "fdk" else {"progress": False}
    if method in ("r2", "gr"):
        opts.update(options)
    out_dir = None
    if logs:
        tag = "_".join([phantom, str(n), method] + [f"{k}-{v}" for k, v in sorted(options.items())])
        out_dir = Path(logs) / tag
    t0 = time.perf_counter()
    _, m = mi_grg.reconstruct(case, method, out_dir=out_dir, **opts)
    out = {"phantom": phantom, "n": n, "method": method, "seconds": time.perf_counter() - t0,
           "psnr_3d": m["psnr_3d"], "ssim_3d": m["ssim_3d"],
           "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
           "variant": m["machine"]["variant"], "code": m["machine"].get("mi_grg"),
           "date": time.strftime("%Y-%m-%d")}
    if method in ("r2", "gr") and options:
        out["options"] = dict(sorted(options.items()))
    info = m.get("method_info")
    if info and method in ("r2", "gr"):
        out.update({k: info[k] for k in ("iterations_run", "iterations_planned", "stopped_by",
                                         "n_gaussians")})
        if "refine" in info:       # gr's default refines after training (its decision)
            out["refine"] = {k: info["refine"].get(k) for k in (
                "lam", "iterations", "at_cap", "decision_seconds", "final_seconds", "skipped")}
        if "result" in info:       # each step's 3-D PSNR (mi_grg.training.result)
            out["parts"] = info["result"].get("parts")
    elif info and "chosen" in info:        # a classical method's held-out decision
        out["chosen"] = info["chosen"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64])
    ap.add_argument("--phantoms", nargs="+", default=["shepp", "needles", "shells"])
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench"))
    ap.add_argument("--fresh", action="store_true",
                    help="drop the cells of an existing reconstruct.json instead of keeping them")
    ap.add_argument("--markdown-only", action="store_true",
                    help="rewrite reconstruct.md from reconstruct.json; run nothing")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a training option for r2 and gr (repeatable)")
    ap.add_argument("--logs", metavar="DIR",
                    help="keep each cell's run files (train_log.csv, metrics.json) under DIR")
    ap.add_argument("--one", nargs=3, metavar=("PHANTOM", "N", "METHOD"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    options = {}
    for kv in args.option:
        k, sep, v = kv.partition("=")
        if not sep or not k:
            ap.error(f"--option {kv!r}: expected KEY=VALUE, e.g. extent=4.5")
        options[k.strip()] = v.strip()
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]), args.one[2], options, args.logs)))
        return 0
    out = Path(args.out)
    old = []
    if (out / "reconstruct.json").exists() and not args.fresh:
        old = json.loads((out / "reconstruct.json").read_text())["rows"]
    if args.markdown_only:
        if not old:
            print(f"--markdown-only: no cells in {out / 'reconstruct.json'}", file=sys.stderr)
            return 2
        write(out, old, [], machine=json.loads((out / "reconstruct.json").read_text())
              .get("machine"))
        return 0
    rows = []
    for n in args.sizes:
        for ph in args.phantoms:
            for method in args.methods:
                extra = [f"--option={kv}" for kv in args.option]
                if args.logs:
                    extra.append(f"--logs={args.logs}")
                r = subprocess.run([sys.executable, __file__, "--one", ph, str(n), method]
                                   + extra,
                                   capture_output=True, text=True, env=dict(os.environ))
                if r.returncode:
                    print(f"{ph} {n} {method} FAILED:\n{r.stderr[-2000:]}", file=sys.stderr)
                    continue
                row = json.loads(r.stdout.strip().splitlines()[-1])
                rows.append(row)
                print(f"{ph:8s} {n:4d}^3 {method:9s} {row['seconds']:8.1f} s  "
                      f"PSNR {row['psnr_3d']:6.2f}  SSIM {row['ssim_3d']:.3f}  "
                      f"peak {row['peak_rss_gb']:.2f} GB", flush=True)
                write(out, old, rows)      # after every cell: a crash loses one cell at most
    new = {key(r) for r in rows}
    kept = [r for r in old if key(r) not in new]
    if kept:
        print(f"kept {len(kept)} cells of the earlier {out / 'reconstruct.json'}")
    return 0


def key(r: dict) -> tuple:
    return (r["phantom"], r["n"], label(r))


def label(r: dict) -> str:
    """The method, with its options if any ("gr (extent=4.5)")."""
    opts = r.get("options") or {}
    return r["method"] + (f" ({', '.join(f'{k}={v}' for k, v in opts.items())})"
                          if opts else "")


def write(out: Path, old: list, rows: list, machine: dict | None = None) -> None:
    """reconstruct.json and .md: the cells measured now, plus the old cells not re-measured
    (``machine``: the one recorded, for a rewrite; default: this one)."""
    new = {key(r) for r in rows}
    order = {m: i for i, m in enumerate(METHODS)}
    rows = sorted([r for r in old if key(r) not in new] + rows,
                  key=lambda r: (r["n"], r["phantom"], order.get(r["method"], 99)))
    out.mkdir(parents=True, exist_ok=True)
    machine = machine or {"cpu": platform.processor() or platform.machine(),
                          "cores": os.cpu_count()}
    tmp = out / "reconstruct.json.tmp"
    tmp.write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))
    tmp.replace(out / "reconstruct.json")
    (out / "reconstruct.md").write_text(to_markdown(rows, machine))


def to_markdown(rows: list, machine: dict) -> str:
    lines = ["# Reconstruction benchmark (`bench/reconstruct.py`)", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, variant "
             f"{rows[0]['variant'] if rows else '?'}. One run per cell (seed 0); 25 noisy "
             "views; 3-D PSNR (dB) / SSIM against the ground truth. Cells measured on "
             "different days (date, code) are not side by side measurements.", "",
             "| phantom | size | method | PSNR | SSIM | time (s) | peak memory (GB) | "
             "iterations | Gaussians | date | code |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        its = (f"{r['iterations_run']}/{r['iterations_planned']}" if "iterations_run" in r
               else "")
        lines.append(f"| {r['phantom']} | {r['n']}^3 | {label(r)} | {r['psnr_3d']:.2f} | "
                     f"{r['ssim_3d']:.3f} | {r['seconds']:.1f} | {r['peak_rss_gb']:.2f} | "
                     f"{its} | {r.get('n_gaussians', '')} | {r.get('date') or '—'} | "
                     f"{r.get('code') or '—'} |")
    # gr against the best classical method and against r2, per case (measured in this run)
    lines += ["", "| phantom | size | gr - best classical (dB) | gr - r2 (dB) | gr - r2 (SSIM) |",
              "|---|---|---|---|---|"]
    cases = sorted({(r["phantom"], r["n"]) for r in rows})
    for ph, n in cases:
        by = {r["method"]: r for r in rows
              if (r["phantom"], r["n"]) == (ph, n) and not r.get("options")}
        classical = [by[m]["psnr_3d"] for m in ("fdk", "sart", "asd-pocs") if m in by]
        if "gr" in by and classical:
            gr, r2 = by["gr"], by.get("r2")
            d_r2 = f"{gr['psnr_3d'] - r2['psnr_3d']:+.2f}" if r2 else "—"
            s_r2 = f"{gr['ssim_3d'] - r2['ssim_3d']:+.3f}" if r2 else "—"
            lines.append(f"| {ph} | {n}^3 | {gr['psnr_3d'] - max(classical):+.2f} | {d_r2} | "
                         f"{s_r2} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
