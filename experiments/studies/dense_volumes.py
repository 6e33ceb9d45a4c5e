"""What a dense micro-CT volume needs from gr / r2: iterations, Gaussians, or both
(issue 21 item 4).

On the suite's dense cases (bone, cement: 64^3, 96^2 detector, 25 noisy views; their source
volumes from $MI_GRG_DATA), one run per variant of the training options, each logging the
3-D PSNR every ``--log-every`` iterations (research logging, excluded from the time) so
the table shows whether it was still rising at the end, with the Gaussian count reached and
the training time. Run it on a quiet machine, one run at a time.

    MI_GRG_DATA=../shared/data .venv/bin/python experiments/studies/dense_volumes.py [--cases bone] \
        [--method gr] [--variants "default:;iterations=3000:iterations=3000"] [--tag NAME]

A variant is NAME:key=value,key=value (training options; empty: the defaults).
Writes docs/bench/dense_volumes.{json,md} (dense_volumes_NAME.* with --tag, so that an
earlier study is kept); the data sets go to $TMPDIR/dense_volumes.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_VARIANTS = ("default:;iterations=3000:iterations=3000;"
                    "cap 1.0/voxel:max_gaussians_per_voxel=1.0")


def parse_variants(text: str) -> list:
    """"NAME:k=v,k=v;NAME2:..." -> [(name, {k: v})] (values as strings, as --option takes)."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(";"))):
        name, _, opts = part.partition(":")
        options = dict(kv.split("=", 1) for kv in filter(None, opts.split(",")))
        out.append((name, options))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="bone")
    ap.add_argument("--method", default="gr", choices=("gr", "r2"))
    ap.add_argument("--variants", default=DEFAULT_VARIANTS)
    ap.add_argument("--log-every", type=int, default=250)
    ap.add_argument("--tag", default="", help="write docs/bench/dense_volumes_TAG.{json,md}")
    ap.add_argument("--suite", default=str(ROOT / "experiments" / "suite_cpu.json"))
    args = ap.parse_args(argv)
    from mi_grg.lab.runner import suite_case
    from mi_grg.lab.suite import load_suite
    from mi_grg.methods import code_version, reconstruct
    suite = load_suite(args.suite)
    code = code_version()          # at the start: the code these runs import
    root = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "dense_volumes"
    rows = []
    for name in args.cases.split(","):
        case = suite_case(suite.case(name), root)
        for variant, options in parse_variants(args.variants):
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            _, m = reconstruct(case, args.method, out_dir=root / "runs" / name / variant,
                               progress=False, log_3d_every=args.log_every, **options)
            info = m["method_info"]
            log = [json.loads(json.dumps(r)) for r in _read_log(root / "runs" / name / variant)]
            curve = [(r["iteration"], round(float(r["psnr_3d"]), 2)) for r in log
                     if r.get("psnr_3d") not in (None, "")]
            heldout = [(r["iteration"], round(float(r["heldout_psnr"]), 2)) for r in log
                       if r.get("heldout_psnr") not in (None, "")]
            rows.append({"case": name, "variant": variant, "options": options,
                         "psnr_3d": round(m["psnr_3d"], 2), "ssim_3d": round(m["ssim_3d"], 4),
                         "iterations": info["iterations_run"], "stopped_by": info["stopped_by"],
                         "n_gaussians": info["n_gaussians"], "cap": info["max_gaussians"],
                         "train_s": round(info["train_seconds"], 1),
                         "wall_s": round(time.perf_counter() - t0, 1),
                         "curve": curve, "heldout_curve": heldout,
                         "best_heldout_psnr": info.get("best_heldout_psnr"),
                         "blurred": blur_scores(root / "runs" / name / variant, case.vol_gt),
                         "load_1min": round(load, 2)})
            print(json.dumps({k: v for k, v in rows[-1].items() if "curve" not in k}))
            _write(rows, args, code)
    return 0


BLUR_SIGMAS = (0.3, 0.5, 0.6, 0.7, 0.85, 1.0)


def blur_scores(run_dir: Path, vol_gt) -> list:
    """[(sigma in voxels, 3-D PSNR of the run's volume after a Gaussian blur of sigma)]:
    an oracle analysis (it reads the ground truth) of how much voxel-scale noise the
    volume carries; nothing in training sees it."""
    import numpy as np
    from scipy.ndimage import gaussian_filter
    from mi_grg.evaluation.metrics import psnr_3d
    vol = np.load(Path(run_dir) / "vol_pred.npy")
    return [(s, round(float(psnr_3d(gaussian_filter(vol, s), vol_gt)), 2)) for s in BLUR_SIGMAS]


def _read_log(run_dir: Path) -> list:
    import csv
    with open(run_dir / "train_log.csv") as f:
        return list(csv.DictReader(f))


def _write(rows, args, code) -> None:
    result = {"method": args.method, "code": code, "cores": os.cpu_count(),
              "log_every": args.log_every, "rows": rows}
    stem = "dense_volumes" + (f"_{args.tag}" if args.tag else "")
    (ROOT / "docs" / "bench").mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "bench" / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (ROOT / "docs" / "bench" / f"{stem}.md").write_text(markdown(result))


def markdown(r: dict) -> str:
    lines = ["# Dense micro-CT volumes: iterations or Gaussians (`experiments/studies/dense_volumes.py`)", "",
             f"{r['method']}, code {r['code']}, {r['cores']} cores, one run per row, one at a "
             f"time; 3-D PSNR logged every {r['log_every']} iterations (not timed).", "",
             "| case | variant | 3-D PSNR | SSIM | iterations | Gaussians (cap) | train (s) "
             "| best held-out PSNR | 3-D PSNR along the run | 3-D PSNR after a blur of sigma "
             "voxels (oracle analysis) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        curve = ", ".join(f"{i}: {p:.2f}" for i, p in x["curve"])
        lines.append(f"| {x['case']} | {x['variant']} | {x['psnr_3d']:.2f} | "
                     f"{x['ssim_3d']:.3f} | {x['iterations']} | {x['n_gaussians']} "
                     f"({x['cap']}) | {x['train_s']:.0f} | {_fmt(x.get('best_heldout_psnr'))} | "
                     f"{curve} | {_blurred(x)} |")
    return "\n".join(lines) + "\n"


def _blurred(row) -> str:
    return ", ".join(f"{s}: {p:.2f}" for s, p in row.get("blurred", [])) or "-"


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
