"""The fit back into the Gaussians, followed: fidelity, 3-D PSNR and time along the fit.

Usage:  .venv/bin/python bench/fit_back.py --out results/cpu128 --cases needles shells
            [--counts 150 300] [--rate-scale 2] [--report docs/bench/fit_back.md]

For each finished gr run of a runner's folder (``OUT/table1/<case>/gr``, with its
checkpoint and metrics.json), the trained state is restored and the result's last two
steps run again as the run made them (``mi_grg.training.result``): the final TV
refinement with the length, weight and anchor form the run decided (read from its
metrics.json, not decided again), then the fit back (``mi_grg.training.distill``) once for
each of ``--counts`` (its ``fit_iterations``: Adam's rates decay over the count, so each
count is its own schedule) at the rates ``--rate-scale`` gives (``fit_rate_scale``). Every
``CHECK_EVERY`` fit iterations the record holds the fit's fidelity to the refined grid,
the 3-D PSNR of its voxelisation against the case's ground truth, and the wall clock. The
fit at the run's own count and rates must score the run's recorded export (a check that
the steps were re-made as they were).
Research only: the ground truth enters no choice of a run.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path


import mi_grg  # noqa: F401  (selects the variant)

def follow(out: Path, case_name: str, counts: list, rate_scale=None) -> dict:
    """The fit's curve for one finished run (module docstring)."""
    import mi_grg.training.distill as distill
    from mi_grg.data.dataset import load_case
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training.config import make_config
    from mi_grg.training.result import (averaged_field, _fit_rates, field_volume,
                                        final_grid)
    from mi_grg.training.trainer import Trainer
    from mi_grg.core.voxelizer import voxelize
    run_dir = out / "table1" / case_name / "gr"
    spec = json.loads((run_dir / "run_spec.json").read_text())
    metrics = json.loads((run_dir / "metrics.json").read_text())
    info = metrics["method_info"]
    refine = info["refine"]
    case = load_case(out / "data" / case_name)
    cfg = make_config("gr", None, **spec["options"])
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(case, cfg, out_dir=tmp, progress=False,
                          resume=run_dir / "checkpoint.npz")
        trainer.run()
        if rate_scale is not None:      # the fit's rates: the training's times this
            trainer.cfg.protocol.fit_rate_scale = rate_scale
        rate_scale = trainer.cfg.protocol.fit_rate_scale
        geo = trainer.case.geometry
        field = averaged_field(trainer, trainer.field_gaussians())
        vol = field_volume(trainer, field)
        grid = final_grid(trainer, field, vol, refine["anchor"]["anchored"],
                          refine["iterations"])
        start = {"iteration": 0, "seconds": 0.0,
                 "fidelity_db": distill.fidelity_db(vol, grid),
                 "psnr_3d": float(psnr_3d(vol, case.vol_gt))}
        fits = []
        for count in counts:
            curve = [start]
            t0 = time.perf_counter()

            def on_check(it, g, db):
                t = time.perf_counter() - t0
                psnr = psnr_3d(voxelize(g, geo, extent=trainer.extent), case.vol_gt)
                curve.append({"iteration": it, "seconds": t, "fidelity_db": db,
                              "psnr_3d": psnr})
                print(f"  {case_name} fit {it:4d}/{count}  {t:7.1f} s  fidelity "
                      f"{db:6.2f} dB  3-D PSNR {psnr:6.3f} dB", flush=True)

            fitted, fit = distill.fit_to_volume(field, geo, grid, lr=_fit_rates(trainer),
                                                iterations=count, extent=trainer.extent,
                                                progress=False, on_check=on_check)
            seconds = time.perf_counter() - t0
            fits.append({"count": count, "rate_scale": rate_scale,
                         "iterations": fit["iterations"],
                         "seconds": seconds, "fidelity_db": fit["fidelity_db"],
                         # the returned fit is the best-fidelity check's
                         "psnr_3d": float(psnr_3d(field_volume(trainer, fitted),
                                                  case.vol_gt)),
                         "curve": curve})
    return {"case": case_name, "out": str(out), "n": int(geo.nVoxel[0]),
            "n_gaussians": info["n_gaussians"],
            "grid_psnr_3d": float(psnr_3d(grid, case.vol_gt)),
            "start": start,
            "recorded": {"psnr_3d": metrics["psnr_3d"],
                         "fit_iterations": int(info["config"]["fit_iterations"]),
                         "fit_seconds": refine["fit"]["seconds"],
                         "seconds": metrics["seconds"]},
            "seconds": time.perf_counter() - t_all, "fits": fits}


def report(results: list, path: Path, command: str) -> None:
    counts = sorted({f["count"] for r in results for f in r["fits"]})
    scales = sorted({f["rate_scale"] for r in results for f in r["fits"]})
    lines = ["# The fit back into the Gaussians, by its iteration count", "",
             "The fit's Adam rates: the training's initial rates times "
             f"{', '.join(f'{x:g}' for x in scales)} (`fit_rate_scale`).", "",
             f"Regenerate: `{command}` ({platform.node()}, {time.strftime('%Y-%m-%d')}). "
             "Each case's finished gr run is restored from its checkpoint, its final "
             "refinement re-made as the run decided it, and the fit back run once per "
             "count (bench/fit_back.py). 3-D PSNR in dB against the ground truth; fit "
             "seconds in brackets.", "",
             "| case | n | Gaussians | field | refined grid | recorded export (count) | "
             + " | ".join(f"fit {c}" for c in counts) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(counts)]
    for r in results:
        by = {f["count"]: f for f in r["fits"]}
        cells = [f"{by[c]['psnr_3d']:.2f} ({by[c]['seconds']:.0f} s)" if c in by else ""
                 for c in counts]
        rec = r["recorded"]
        lines.append(f"| {r['case']} | {r['n']} | {r['n_gaussians']} | "
                     f"{r['start']['psnr_3d']:.2f} | {r['grid_psnr_3d']:.2f} | "
                     f"{rec['psnr_3d']:.2f} ({rec['fit_iterations']}) | "
                     + " | ".join(cells) + " |")
    lines += ["", "Along each fit (iteration: fidelity to the grid / 3-D PSNR, dB):", ""]
    for r in results:
        for f in r["fits"]:
            pts = ", ".join(f"{c['iteration']}: {c['fidelity_db']:.1f} / {c['psnr_3d']:.2f}"
                            for c in f["curve"])
            lines.append(f"- {r['case']} ({r['n']}^3), count {f['count']}: {pts}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    path.with_suffix(".json").write_text(json.dumps(results, indent=1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="a runner's output folder")
    p.add_argument("--cases", nargs="+", required=True)
    p.add_argument("--counts", type=int, nargs="+", default=[300])
    p.add_argument("--rate-scale", type=float, default=None,
                   help="the fit's Adam rates: the training's initial rates times this "
                        "(default: today's fit_rate_scale; runs before it used 1)")
    p.add_argument("--report", type=Path, default=Path("docs/bench/fit_back.md"))
    a = p.parse_args(argv)
    results = []
    for c in a.cases:
        results.append(follow(a.out, c, a.counts, a.rate_scale))
        report(results, a.report, "python bench/fit_back.py " + " ".join(
            sys.argv[1:] if argv is None else argv))
    print(f"wrote {a.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
