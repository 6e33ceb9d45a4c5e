"""Benchmark: how strong are GR-Gaussian's graph terms against the data term, at the paper's weights?

    .venv/bin/python experiments/studies/graph_terms.py [--results results/cpu] [--cases shepp shell bone]
                                          [--view-step 3]

For each case, the trained gr state of the experiment suite's Table 1
(RESULTS/table1/CASE/gr/gaussians.npz, data RESULTS/data/CASE; run ``experiments/run_cpu.sh``
first) is loaded with the graph of its own centres, and two ratios are measured per Gaussian,
on every --view-step-th training view:

  Laplacian:  |d(lambda_lap (REFERENCE_N / N) L_lap) / d rho_i|  against the per-step data
              gradient |d(L1 + lambda_ssim D-SSIM) / d rho_i| of one view (mean over views);
              both with the graph field's multiplier, as in training.
  PGA:        lambda_g x mean_j |rho_i - rho_j| (the graph term added to the densification
              statistic) against the detector-plane positional gradient in NDC units,
              averaged over the views that see the Gaussian (the statistic it is added to);
              also how many Gaussians the graph term lifts over tau_pos.

A ratio of 1 % means the term moves a Gaussian 1 % as hard as the projections do. Medians
over Gaussians. Writes docs/bench/graph_terms.md and docs/bench/graph_terms.json.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
from pathlib import Path

import numpy as np

import mi_grg
import drjit as dr
import mitsuba as mi

from mi_grg.training.config import make_config
from mi_grg.data.dataset import load_case
from mi_grg.core.gaussians import Gaussians
from mi_grg.training.graph import (build_graph, graph_density_scale, laplacian_loss,
                          mean_abs_density_difference)
from mi_grg.training.losses import projection_loss
from mi_grg.core.projector import project_dr
from mi_grg.training.trainer import REFERENCE_N

ROOT = Path(__file__).resolve().parents[2]


def measure(case_dir: Path, run_dir: Path, view_step: int) -> dict:
    cfg = make_config("gr")
    case = load_case(case_dir)
    geo = case.geometry
    g0 = Gaussians.load_npz(run_dir / "gaussians.npz")
    n = len(g0)
    graph = build_graph(g0.positions, k=cfg.graph.k, s=cfg.graph.graph_s)
    m = graph_density_scale(graph)
    rho = mi.Float(g0.densities)
    dr.enable_grad(rho)
    g = g0.replace(densities=rho)
    nv, nu = geo.nDetector
    ndc = np.array([nu / 2.0, nv / 2.0])          # pixel -> NDC, as in training
    views = range(0, geo.n_views, view_step)
    data_abs = np.zeros(n)
    pos_sum, pos_seen = np.zeros(n), np.zeros(n)
    for view in views:
        dr.clear_grad(rho)
        means2d = dr.zeros(mi.Vector2f, n)
        dr.enable_grad(means2d)
        img = project_dr(g, geo, angles=geo.angles[view:view + 1], extent=cfg.schedule.extent,
                         density_scale=m, means2d=means2d)
        target = mi.TensorXf(np.ascontiguousarray(case.train[view], np.float32))
        pred = mi.TensorXf(img.array, (nv, nu))
        dr.backward(projection_loss(pred, target, cfg.losses.lambda_ssim))
        data_abs += np.abs(np.asarray(dr.grad(rho)))
        g2 = dr.grad(means2d)
        gn = np.hypot(np.asarray(g2.x) * ndc[0], np.asarray(g2.y) * ndc[1])
        pos_sum += gn
        pos_seen += gn > 0
    data_abs /= len(views)
    dr.clear_grad(rho)
    dr.backward(cfg.graph.lambda_lap * (REFERENCE_N / n)
                * laplacian_loss(graph, rho, normalise=False))
    lap_abs = np.abs(np.asarray(dr.grad(rho)))
    pos = pos_sum / np.maximum(pos_seen, 1)
    pga = cfg.densify.lambda_g * np.asarray(mean_abs_density_difference(graph, dr.detach(rho)))
    seen = pos_seen > 0
    lifted = int(np.sum(seen & (pos <= cfg.densify.densify_grad_threshold)
                        & (pos + pga > cfg.densify.densify_grad_threshold)))
    tiny = 1e-30
    lap_ratio = lap_abs / np.maximum(data_abs, tiny)
    return {"case": case_dir.name, "n_gaussians": n, "edges": graph.num_edges,
            "views": len(views), "rho_median": float(np.median(np.asarray(rho))),
            "data_grad_median": float(np.median(data_abs)),
            "lap_grad_median": float(np.median(lap_abs)),
            "lap_ratio_median": float(np.median(lap_ratio)),
            "lap_ratio_p90": float(np.percentile(lap_ratio, 90)),
            "pos_grad_median": float(np.median(pos[seen])),
            "pga_term_median": float(np.median(pga[seen])),
            "pga_ratio_median": float(np.median(pga[seen] / np.maximum(pos[seen], tiny))),
            "above_tau_pos": int(np.sum(seen & (pos > cfg.densify.densify_grad_threshold))),
            "lifted_by_pga": lifted}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results" / "cpu")
    ap.add_argument("--cases", nargs="+", default=["shepp", "shell", "bone"])
    ap.add_argument("--view-step", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench")
    a = ap.parse_args(argv)
    if a.view_step < 1:
        ap.error(f"--view-step must be >= 1, got {a.view_step}")
    rows = []
    for c in a.cases:
        case_dir, run_dir = a.results / "data" / c, a.results / "table1" / c / "gr"
        for p in (case_dir, run_dir / "gaussians.npz"):
            if not p.exists():
                ap.error(f"{p} is missing: run experiments/run_cpu.sh (Table 1) first")
        rows.append(measure(case_dir, run_dir, a.view_step))
        print(json.dumps(rows[-1]))
    cfg = make_config("gr")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    try:
        shown = a.results.resolve().relative_to(ROOT)
    except ValueError:
        shown = a.results
    meta = {"commit": commit, "machine": platform.processor() or platform.machine(),
            "lambda_lap": cfg.graph.lambda_lap, "lambda_g": cfg.densify.lambda_g,
            "tau_pos": cfg.densify.densify_grad_threshold, "results": str(shown)}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "graph_terms.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        "# Graph terms against the data term (`experiments/studies/graph_terms.py`)", "",
        f"Trained gr states of Table 1 ({shown}), commit {commit}; lambda_lap = "
        f"{cfg.graph.lambda_lap:g}, lambda_g = {cfg.densify.lambda_g:g}, tau_pos = "
        f"{cfg.densify.densify_grad_threshold:g}. Medians over Gaussians; 'ratio' = graph term "
        "/ data term per Gaussian.", "",
        "| case | Gaussians | median rho | Laplacian / data gradient on rho (median, 90th pct.) "
        "| PGA term / positional gradient (median) | above tau_pos | lifted over tau_pos by PGA |",
        "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['n_gaussians']} | {r['rho_median']:.2g} | "
                     f"{100 * r['lap_ratio_median']:.2f} %, {100 * r['lap_ratio_p90']:.2f} % | "
                     f"{100 * r['pga_ratio_median']:.2f} % | {r['above_tau_pos']} | "
                     f"{r['lifted_by_pga']} |")
    (a.out / "graph_terms.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
