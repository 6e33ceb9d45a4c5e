"""Benchmark of the classical baselines (FDK, SART, ASD-POCS) against RTK's CPU filters.

Case: Shepp-Logan (mi_grg.data.phantoms), R2-Gaussian's synthetic scanner
(mi_grg.data.simulate.default_geometry) at 64^3 / 96^2 and 128^3 / 192^2, 25 views, TIGRE noise
(I0 = 1e4, electronic std 10). Every timing is a median of >= 3 runs after a JIT warm-up
run, whose time is reported separately; the RTK runs use the same data, geometry and
machine in the same process, so the ratios compare like with like.

Writes docs/bench/baselines.json and docs/bench/baselines.md.
Usage: .venv/bin/python bench/baselines.py [--sizes 64 128] [--reps 3] [--no-rtk]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import mi_grg  # noqa: F401  (before mitsuba / drjit)
import drjit as dr
import mitsuba as mi

from mi_grg.core.fdk import fdk, fdk_backproject, filter_projections
from mi_grg.classical.iterative import asd_pocs, sart
from mi_grg.evaluation.metrics import psnr_3d, ssim_3d
from mi_grg.data.noise import NoiseModel
from mi_grg.data.phantoms import make_phantom
from mi_grg.data.simulate import default_geometry
from mi_grg.core.joseph import JosephProjector

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))          # the RTK geometry mapping lives there

DETECTOR = {64: 96, 128: 192}
N_VIEWS = 25
SART_ITERS = 10


def timed(fn, reps):
    """(result of the warm-up call, warm-up seconds, median of ``reps`` further runs, all)."""
    t = time.perf_counter()
    out = fn()
    dr.sync_thread()
    warm = time.perf_counter() - t
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        out = fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return out, warm, statistics.median(times), times


def quality(vol, gt):
    return {"psnr": psnr_3d(vol, gt), "ssim": ssim_3d(vol, gt)}


class _ADJoseph(JosephProjector):
    """The forward loop with Dr.Jit's sum-style reverse-mode hint, to time A^T by AD."""

    @dr.syntax
    def _forward_chunk(self, vol, tables, n_rays, view0):
        st = self._setup(tables, n_rays, view0)
        i = mi.Int32(st["i0"])
        acc = dr.zeros(mi.Float, n_rays)
        while dr.hint(i <= st["i1"], max_iterations=-1):
            idx, wts, msk = self._sample(st, i)
            for j in range(4):
                acc += wts[j] * dr.gather(mi.Float, vol, idx[j], msk[j],
                                          mode=dr.ReduceMode.Expand)
            i += 1
        return acc


def projector_rates(geo, reps):
    """Voxels x views per second of A, A^T (scatter), A^T (AD) and the FDK back-projection."""
    A = JosephProjector(geo)
    rng = np.random.default_rng(0)
    x = mi.Float(rng.uniform(0, 1, A.n_vox).astype(np.float32))
    y = mi.Float(rng.uniform(0, 1, geo.n_views * A.n_pix).astype(np.float32))
    work = A.n_vox * geo.n_views
    out = {}
    _, w, t, _ = timed(lambda: A.forward(x, geo.angles), reps)
    out["forward"] = {"seconds": t, "warmup_s": w, "voxel_views_per_s": work / t}
    _, w, t, _ = timed(lambda: A.adjoint(y, geo.angles), reps)
    out["adjoint_scatter"] = {"seconds": t, "warmup_s": w, "voxel_views_per_s": work / t}
    ad = _ADJoseph(geo)

    def adjoint_ad():
        xx = mi.Float(x)
        dr.enable_grad(xx)
        p = ad._forward_chunk(xx, ad.angle_tables(geo.angles), geo.n_views * ad.n_pix, 0)
        dr.backward(dr.sum(p * y))
        g = dr.grad(xx)
        dr.eval(g)
        return g
    g, w, t, _ = timed(adjoint_ad, reps)
    diff = float(np.abs(g.numpy() - A.adjoint(y, geo.angles).numpy()).max())
    out["adjoint_ad"] = {"seconds": t, "warmup_s": w, "voxel_views_per_s": work / t,
                         "max_abs_diff_to_scatter": diff,
                         "note": "forward + dr.backward (the forward pass is included)"}
    q = np.ascontiguousarray(y.numpy().reshape(geo.projection_shape))
    _, w, t, _ = timed(lambda: fdk_backproject(q, geo), reps)
    out["fdk_backprojection"] = {"seconds": t, "warmup_s": w, "voxel_views_per_s": work / t}
    return out


def rtk_runs(geo, proj, gt, reps):
    from test_voxel_projector import (from_rtk_volume, rtk_geometry, to_rtk_projections,
                                      to_rtk_volume)
    import itk
    from itk import RTK as rtk
    IF3 = itk.Image[itk.F, 3]
    rg = rtk_geometry(rtk, geo)
    # fresh ITK inputs for every run: RTK's filters may run in place on their inputs
    zeros = np.zeros(geo.nVoxel, np.float32)
    res = {}

    def run_fdk():
        f = rtk.FDKConeBeamReconstructionFilter[IF3].New()
        f.SetInput(0, to_rtk_volume(itk, zeros, geo))
        f.SetInput(1, to_rtk_projections(itk, proj, geo))
        f.SetGeometry(rg)
        f.GetRampFilter().SetTruncationCorrection(0.0)
        f.Update()
        return from_rtk_volume(itk, f.GetOutput())
    vol, w, t, ts = timed(run_fdk, reps)
    res["fdk"] = {"seconds": t, "first_call_s": w, "runs_s": ts, **quality(vol, gt)}

    def run_sart(n_iter):
        f = rtk.SARTConeBeamReconstructionFilter[IF3, IF3].New()
        f.SetInput(0, to_rtk_volume(itk, zeros, geo))
        f.SetInput(1, to_rtk_projections(itk, proj, geo))
        f.SetGeometry(rg)
        f.SetNumberOfIterations(n_iter)
        f.SetEnforcePositivity(True)
        f.Update()
        return from_rtk_volume(itk, f.GetOutput()), f.GetLambda()
    (vol, lam), w, t, ts = timed(lambda: run_sart(1), reps)
    res["sart_sweep"] = {"seconds": t, "first_call_s": w, "runs_s": ts}
    t0 = time.perf_counter()
    vol, lam = run_sart(SART_ITERS)
    res["sart"] = {"seconds": time.perf_counter() - t0, "n_iter": SART_ITERS, "lambda": lam,
                   **quality(vol, gt)}
    fp = rtk.JosephForwardProjectionImageFilter[IF3, IF3].New()
    work = int(np.prod(geo.nVoxel)) * geo.n_views

    def run_fp():
        f = rtk.JosephForwardProjectionImageFilter[IF3, IF3].New()
        f.SetInput(0, to_rtk_projections(itk, np.zeros_like(proj), geo))
        f.SetInput(1, to_rtk_volume(itk, gt, geo))
        f.SetGeometry(rg)
        f.Update()
        return f.GetOutput()
    del fp
    _, w, t, _ = timed(run_fp, reps)
    res["forward"] = {"seconds": t, "voxel_views_per_s": work / t}

    def run_bp():
        f = rtk.JosephBackProjectionImageFilter[IF3, IF3].New()
        f.SetInput(0, to_rtk_volume(itk, zeros, geo))
        f.SetInput(1, to_rtk_projections(itk, proj, geo))
        f.SetGeometry(rg)
        f.Update()
        return f.GetOutput()
    _, w, t, _ = timed(run_bp, reps)
    res["adjoint_joseph_back"] = {"seconds": t, "voxel_views_per_s": work / t}
    return res


def iterative_run(fn, proj, geo, gt, **kw):
    """One full run; per-sweep times from the callback (median), set-up time separately."""
    stamps = []
    t0 = time.perf_counter()
    vol = fn(proj, geo, progress=False, callback=lambda it, v: stamps.append(time.perf_counter()),
             **kw)
    total = time.perf_counter() - t0
    # the callback itself converts the volume to numpy: negligible against a sweep
    per = np.diff(stamps)
    return {"seconds": total, "n_iter": len(stamps),
            "first_iteration_s": stamps[0] - t0 if stamps else None,
            "median_iteration_s": float(np.median(per)) if per.size else None,
            **quality(vol, gt)}


def bench_size(n, reps, with_rtk):
    det = DETECTOR[n]
    geo = default_geometry(n, det, N_VIEWS)
    ph = make_phantom("shepp")
    gt = ph.voxelize(geo, 2)
    clean = ph.line_integrals(geo)
    proj = NoiseModel(I0=1e4, electronic_std=10).apply(clean, np.random.default_rng(0))
    r = {"nVoxel": list(geo.nVoxel), "nDetector": list(geo.nDetector), "n_views": N_VIEWS}
    vol, w, t, ts = timed(lambda: fdk(proj, geo), reps)
    r["fdk"] = {"seconds": t, "warmup_s": w, "runs_s": ts, **quality(vol, gt)}
    q = filter_projections(proj, geo)
    _, _, t_filter, _ = timed(lambda: filter_projections(proj, geo), reps)
    r["fdk"]["filter_s"] = t_filter
    del q
    # one SART sweep including its weights (what `sart(n_iter=1)` costs), then full runs
    _, w, t, ts = timed(lambda: sart(proj, geo, n_iter=1, progress=False), reps)
    r["sart_sweep_with_setup"] = {"seconds": t, "warmup_s": w, "runs_s": ts}
    r["sart"] = iterative_run(sart, proj, geo, gt, n_iter=SART_ITERS)
    r["os_sart_bs5"] = iterative_run(sart, proj, geo, gt, n_iter=SART_ITERS, blocksize=5)
    r["asd_pocs"] = iterative_run(asd_pocs, proj, geo, gt, n_iter=SART_ITERS)
    r["projector"] = projector_rates(geo, reps)
    if with_rtk:
        r["rtk"] = rtk_runs(geo, proj, gt, reps)
        rt = r["rtk"]
        r["ratios"] = {
            "fdk_time_ours_over_rtk": r["fdk"]["seconds"] / rt["fdk"]["seconds"],
            "sart_sweep_ours_over_rtk": r["sart"]["median_iteration_s"]
            / rt["sart_sweep"]["seconds"],
            "forward_ours_over_rtk": r["projector"]["forward"]["seconds"]
            / rt["forward"]["seconds"],
            "adjoint_ours_over_rtk_joseph_back": r["projector"]["adjoint_scatter"]["seconds"]
            / rt["adjoint_joseph_back"]["seconds"],
        }
    return r


def rtk_reference_case(reps):
    """The brief's reference: RTK took ~0.2 s for FDK of 64^3 from 50 views of 96^2."""
    geo = default_geometry(64, 96, 50)
    ph = make_phantom("shepp")
    proj = ph.line_integrals(geo).astype(np.float32)
    gt = ph.voxelize(geo, 2)
    _, w, t, _ = timed(lambda: fdk(proj, geo), reps)
    out = {"ours_fdk_s": t, "ours_warmup_s": w}
    try:
        out["rtk_fdk_s"] = rtk_runs_fdk_only(geo, proj, reps)
        out["ratio_ours_over_rtk"] = t / out["rtk_fdk_s"]
    except ImportError:
        pass
    del gt
    return out


def rtk_runs_fdk_only(geo, proj, reps):
    from test_voxel_projector import (rtk_geometry, to_rtk_projections, to_rtk_volume)
    import itk
    from itk import RTK as rtk
    IF3 = itk.Image[itk.F, 3]
    rg = rtk_geometry(rtk, geo)
    zeros = np.zeros(geo.nVoxel, np.float32)

    def run():
        f = rtk.FDKConeBeamReconstructionFilter[IF3].New()
        f.SetInput(0, to_rtk_volume(itk, zeros, geo))
        f.SetInput(1, to_rtk_projections(itk, proj, geo))
        f.SetGeometry(rg)
        f.GetRampFilter().SetTruncationCorrection(0.0)
        f.Update()
        return f.GetOutput()
    return timed(run, reps)[2]


def write_markdown(res, path):
    L = ["# Classical baselines: FDK, SART, ASD-POCS (Dr.Jit) vs RTK (CPU)", "",
         f"Machine: {res['machine']['cpu']}, {res['machine']['cores']} cores, variant "
         f"{res['machine']['variant']}, Dr.Jit {res['machine']['drjit']}, itk-rtk "
         f"{res['machine'].get('itk_rtk', 'absent')}. Shepp-Logan, 25 views, TIGRE noise "
         "(I0 = 1e4, electronic std 10). Times are medians of "
         f"{res['reps']} runs after a warm-up run (JIT compilation) whose time is listed "
         "separately; full iterative runs are single runs, with the median time per "
         "iteration. Generated by `bench/baselines.py`.", "",
         "Load average (1, 5, 15 min) at start "
         + ", ".join(f"{x:.1f}" for x in res["load_average_start"]) + ", at end "
         + ", ".join(f"{x:.1f}" for x in res["load_average_end"])
         + ": on this shared 2-core machine a load above ~1 means other processes took "
         "CPU time from the run, and repeated runs vary by 2-3x in absolute time; the "
         "ours/RTK ratios are taken back to back and are steadier.", ""]
    for key, r in res["sizes"].items():
        L += [f"## {r['nVoxel'][0]}^3 volume, {r['nDetector'][0]}^2 detector, "
              f"{r['n_views']} views", "",
              "| method | time (s) | warm-up (s) | PSNR (dB) | SSIM |", "|---|---|---|---|---|"]
        f = r["fdk"]
        L.append(f"| FDK (ours) | {f['seconds']:.3f} | {f['warmup_s']:.2f} | {f['psnr']:.2f} "
                 f"| {f['ssim']:.3f} |")
        for name, label in (("sart", "SART"), ("os_sart_bs5", "OS-SART (5 views/subset)"),
                            ("asd_pocs", "ASD-POCS")):
            s = r[name]
            L.append(f"| {label}, {s['n_iter']} it. (ours) | {s['seconds']:.2f} "
                     f"({s['median_iteration_s']:.3f}/it.) | first it. "
                     f"{s['first_iteration_s']:.2f} | {s['psnr']:.2f} | {s['ssim']:.3f} |")
        if "rtk" in r:
            rt = r["rtk"]
            L.append(f"| FDK (RTK) | {rt['fdk']['seconds']:.3f} | {rt['fdk']['first_call_s']:.2f}"
                     f" | {rt['fdk']['psnr']:.2f} | {rt['fdk']['ssim']:.3f} |")
            L.append(f"| SART, {rt['sart']['n_iter']} it., lambda {rt['sart']['lambda']} (RTK) "
                     f"| {rt['sart']['seconds']:.2f} ({rt['sart_sweep']['seconds']:.3f}/it.) "
                     f"| | {rt['sart']['psnr']:.2f} | {rt['sart']['ssim']:.3f} |")
        s1 = r["sart_sweep_with_setup"]
        L += ["", f"One SART sweep including its weights (`sart(n_iter=1)`): "
              f"{s1['seconds']:.3f} s (warm-up {s1['warmup_s']:.2f} s).", "",
              "| operator | time (s) | voxels x views / s |", "|---|---|---|"]
        for name, p in r["projector"].items():
            L.append(f"| {name} (ours) | {p['seconds']:.3f} | {p['voxel_views_per_s']:.3g} |")
        if "rtk" in r:
            for name in ("forward", "adjoint_joseph_back"):
                p = r["rtk"][name]
                L.append(f"| {name} (RTK) | {p['seconds']:.3f} | "
                         f"{p['voxel_views_per_s']:.3g} |")
            L += ["", "Ratios ours / RTK (time, < 1 = we are faster): " + ", ".join(
                f"{k} {v:.2f}" for k, v in r["ratios"].items())]
        L.append("")
    ref = res.get("reference_64_50views")
    if ref:
        L += ["## Reference case: FDK of 64^3 from 50 views of 96^2", "",
              f"ours {ref['ours_fdk_s']:.3f} s"
              + (f", RTK {ref['rtk_fdk_s']:.3f} s, ratio {ref['ratio_ours_over_rtk']:.2f}"
                 if "rtk_fdk_s" in ref else ""), ""]
    L += ["## Targets (this 2-core CPU)", ""]
    big = res["sizes"].get("128")
    if big:
        t = big["fdk"]["seconds"]
        L.append(f"- FDK of 128^3 from 25 views of 192^2 <= 2 s: {t:.3f} s "
                 f"({'met' if t <= 2 else 'MISSED'}).")
        t = big["sart"]["median_iteration_s"]
        L.append(f"- One SART sweep at that size <= 2 s: {t:.3f} s per sweep "
                 f"({'met' if t <= 2 else 'MISSED'}); with the one-off weights "
                 f"(`sart(n_iter=1)`) {big['sart_sweep_with_setup']['seconds']:.3f} s.")
    if ref and "rtk_fdk_s" in ref:
        L.append(f"- FDK at least as fast as RTK's (64^3, 50 views of 96^2): ratio "
                 f"{ref['ratio_ours_over_rtk']:.2f} "
                 f"({'met' if ref['ratio_ours_over_rtk'] <= 1 else 'MISSED'}).")
    L += ["", "## Notes", "",
          "- The back projector is the transposed scatter of the forward projector's "
          "weights (`scatter_add`, ReduceMode.Expand on the LLVM backend). Dr.Jit AD "
          "(`dr.backward` through the forward loop, which needs the loop hint "
          "`max_iterations=-1`) gives the same operator (max |difference| in the JSON, "
          "float32 rounding) but is slower: the row `adjoint_ad` includes its forward "
          "pass, which AD cannot skip.",
          "- RTK's back projector here is its Joseph back projection (the adjoint, as "
          "ours); RTK's SART uses its own default lambda (0.3) and projectors, so its "
          "PSNR differs from ours by more than rounding.",
          "- SART and ASD-POCS semi-converge on these noisy 25-view data (see "
          "`mi_grg/iterative.py`); PSNR/SSIM use `mi_grg.evaluation.metrics` (data range 1).", ""]
    path.write_text("\n".join(L) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128], choices=sorted(DETECTOR))
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-rtk", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench")
    args = ap.parse_args(argv)
    with_rtk = not args.no_rtk
    machine = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
               "variant": mi.variant(), "drjit": dr.__version__,
               "threads": dr.thread_count()}
    if with_rtk:
        try:
            import importlib.metadata as md
            import itk  # noqa: F401
            from itk import RTK  # noqa: F401
            machine["itk_rtk"] = md.version("itk-rtk")
        except Exception as exc:
            print(f"RTK unavailable ({exc}); running without it", file=sys.stderr)
            with_rtk = False
    # other processes on a shared machine inflate the timings: record the load
    res = {"machine": machine, "reps": args.reps, "sizes": {},
           "load_average_start": os.getloadavg()}
    for n in args.sizes:
        print(f"== {n}^3", file=sys.stderr, flush=True)
        res["sizes"][str(n)] = bench_size(n, args.reps, with_rtk)
    res["reference_64_50views"] = rtk_reference_case(args.reps) if with_rtk else None
    res["load_average_end"] = os.getloadavg()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "baselines.json").write_text(json.dumps(res, indent=2))
    write_markdown(res, args.out / "baselines.md")
    print((args.out / "baselines.md").read_text())


if __name__ == "__main__":
    main()
