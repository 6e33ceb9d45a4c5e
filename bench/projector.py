"""Benchmark of the radiative-Gaussian projector (mi_grg.core.projector), CPU (LLVM) or GPU.

    .venv/bin/python bench/projector.py            # full grid (a few minutes on 2 cores)
    .venv/bin/python bench/projector.py --quick    # smoke run
    .venv/bin/python bench/projector.py --variant cuda_ad_mono   # on a GPU

Writes ``docs/bench/projector.json`` and ``docs/bench/projector.md`` (``projector_cuda.*``
with ``--variant cuda_ad_mono``, where peak RSS is host memory only). Every configuration
runs in its own subprocess (peak memory = that process's ru_maxrss, which sees Dr.Jit's
allocations). Times are medians of ``--runs`` calls after one warm-up call; the warm-up
(JIT compilation or kernel-cache load) is reported separately.

Workload: N Gaussians uniform in the unit ball, scales = 0.5 x the mean distance to the 3
nearest neighbours (R2-Gaussian's initialisation uses that distance) with log-normal
anisotropy (sigma 0.3 per axis), random rotations; one cone-beam view (DSO 5, DSD 7,
detector 3.2 x 3.2 covering the ball), i.e. one training iteration. "Pairs" are the
(Gaussian, pixel) evaluations the kernels perform (pixels inside each exact footprint).
Forward+backward differentiates <projection, y> w.r.t. positions, scales, rotations,
densities and the detector-plane offsets (means2d), as training does.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"fwd_pairs_per_s": 60e6, "fwdbwd_pairs_per_s": 20e6, "fwdbwd_50k_256_s": 1.0,
           "peak_rss_gb": 2.0}


# ====================================================================== worker side
def _workload(n, nd, seed=0, views=1):
    import numpy as np
    from scipy.spatial import cKDTree
    import mi_grg
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.geometry import circular_angles
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    x *= (rng.uniform(0, 1, (n, 1)) ** (1 / 3)) / np.linalg.norm(x, axis=1, keepdims=True)
    dist, _ = cKDTree(x).query(x, k=4)
    s = 0.5 * dist[:, 1:].mean(1, keepdims=True) * np.exp(rng.normal(0, 0.3, (n, 3)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians.from_numpy(x, s, q, rng.uniform(0.1, 1.0, n))
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(nd, nd),
                          sDetector=(3.2, 3.2), nVoxel=(64, 64, 64), sVoxel=(2.0, 2.0, 2.0),
                          angles=circular_angles(views) + 0.1)
    return g, geo, (x, s, q)


def _timed(fn, runs):
    import drjit as dr
    times = []
    for _ in range(runs):
        dr.sync_thread()
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return times


def _fwd_bwd_fns(g, geo, extent, views):
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    from mi_grg.core.projector import project_dr
    nv, nu = geo.nDetector
    y = mi.Float(np.random.default_rng(1).normal(size=views * nv * nu).astype(np.float32))

    def fwd():
        img = project_dr(g, geo, extent=extent)
        dr.eval(img)

    def fwd_bwd():
        leaves = [type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)]
        for a in leaves:
            dr.enable_grad(a)
        md = dr.zeros(mi.Vector2f, len(g) * views)
        dr.enable_grad(md)
        img = project_dr(type(g)(*leaves), geo, extent=extent, means2d=md)
        dr.backward(dr.sum(img.array * y))
        dr.eval([dr.grad(a) for a in leaves], dr.grad(md))
    return fwd, fwd_bwd


@contextlib.contextmanager
def profiled(book: dict):
    """Phase times (s) and work counts of the projector's passes inside the block, booked
    into ``book``. The bench wraps the projector's steps with synchronising timers (the
    projector itself never synchronises for them): chunk classification, the pixel
    kernels per mode, and Dr.Jit AD from the record parameters to the Gaussians."""
    import drjit as dr
    import mitsuba as mi
    from mi_grg.core import projector as P
    from mi_grg.core.projector_kernels import lane_values

    def add(key, value):
        book[key] = book.get(key, 0) + value

    def timed(name_of, fn, before=None, after=None, count=None):
        def wrapper(*args, **kwargs):
            if before is not None:
                before(*args)
            dr.sync_thread()
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            if after is not None:
                after(out, *args)
            dr.sync_thread()
            add(name_of(*args), time.perf_counter() - t0)
            if count is not None:
                count(out)
            return out
        return wrapper

    def count_pixels(mode, det, arrays, vbase, rec, row, *rest):
        if mode != dr.ADMode.Primal:
            return
        with dr.suspend_grad():
            *_, lo, hi = lane_values(det, *arrays, rec, row)
            cnt = dr.sum(mi.Float(dr.maximum(hi - lo + 1, 0)), axis=None)
        add("pixels_regular", int(cnt[0]))

    def eval_kernel(out, mode, det, arrays, vbase, rec, row, image, *rest):
        dr.eval(image if out is None else out)

    def count_chunk(prep):
        add("records_regular", prep.n_reg)
        add("records_near", prep.n_near)
        if prep.n_reg:
            add("rows_regular", int(dr.sum(prep.footprint["n_rows"], axis=None)[0]))

    saved = (P.PreparedChunk, P.regular_kernel, P.near_kernel, P._ProjectOp._backward_to_leaves)
    P.PreparedChunk = timed(lambda *a: "classify", P.PreparedChunk, count=count_chunk)
    P.regular_kernel = timed(lambda mode, *a: "kernel_" + mode.name.lower(), P.regular_kernel,
                             before=count_pixels, after=eval_kernel)
    P.near_kernel = timed(lambda mode, *a: "kernel_near_" + mode.name.lower(), P.near_kernel,
                          after=eval_kernel)
    P._ProjectOp._backward_to_leaves = timed(lambda *a: "ad_backward", saved[3])
    try:
        dr.sync_thread()
        t0 = time.perf_counter()
        yield book
        dr.sync_thread()
        phases = sum(v for k, v in book.items() if isinstance(v, float))
        add("other", time.perf_counter() - t0 - phases)
    finally:
        (P.PreparedChunk, P.regular_kernel, P.near_kernel,
         P._ProjectOp._backward_to_leaves) = saved


def _pairs(g, geo, extent):
    """(Gaussian, pixel) evaluations of one forward pass, from the bench's profiler."""
    import drjit as dr
    from mi_grg.core import projector as P
    prof = {}
    with profiled(prof), dr.suspend_grad():
        dr.eval(P.project_dr(g, geo, extent=extent))
    return int(prof.get("pixels_regular", 0)), prof


def worker_grid(cfg):
    import resource
    from mi_grg.core.projector import DEFAULT_EXTENT
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    t0 = time.perf_counter()
    g, geo, _ = _workload(cfg["n"], cfg["nd"], views=cfg.get("views", 1))
    setup = time.perf_counter() - t0
    extent = cfg.get("extent", DEFAULT_EXTENT)
    fwd, fwd_bwd = _fwd_bwd_fns(g, geo, extent, cfg.get("views", 1))
    first_fwd = _timed(fwd, 1)[0]
    first_fb = _timed(fwd_bwd, 1)[0]
    tf = _timed(fwd, cfg["runs"])
    tfb = _timed(fwd_bwd, cfg["runs"])
    pairs, prof = _pairs(g, geo, extent)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2   # KiB -> GiB
    return {"n": cfg["n"], "nd": cfg["nd"], "views": cfg.get("views", 1), "extent": extent,
            "pairs": pairs, "records": prof.get("records_regular", 0),
            "rows": prof.get("rows_regular", 0), "records_near": prof.get("records_near", 0),
            "fwd_s": statistics.median(tf), "fwdbwd_s": statistics.median(tfb),
            "fwd_runs": tf, "fwdbwd_runs": tfb, "first_fwd_s": first_fwd,
            "first_fwdbwd_s": first_fb, "setup_s": setup, "peak_rss_gb": rss,
            "baseline_rss_gb": base_rss}


def worker_phases(cfg):
    """Where the time goes (profiled run: synchronises between phases)."""
    from mi_grg.core import projector as P
    g, geo, _ = _workload(cfg["n"], cfg["nd"])
    _, fwd_bwd = _fwd_bwd_fns(g, geo, P.DEFAULT_EXTENT, 1)
    fwd_bwd()
    out = []
    for _ in range(cfg["runs"]):
        with profiled({}) as book:
            fwd_bwd()
        out.append(book)
    keys = [k for k in out[0] if isinstance(out[0][k], float)]
    return {k: statistics.median(o.get(k, 0.0) for o in out) for k in keys}


def worker_extent(cfg):
    import numpy as np
    from mi_grg.core.projector import project
    g, geo, _ = _workload(cfg["n"], cfg["nd"])
    ref = project(g, geo, extent=9.0).astype(np.float64)    # truncation exp(-40.5) ~ 3e-18
    rows = []
    for e in cfg["extents"]:
        fwd, fwd_bwd = _fwd_bwd_fns(g, geo, e, 1)
        fwd()
        fwd_bwd()
        tf = statistics.median(_timed(fwd, cfg["runs"]))
        tfb = statistics.median(_timed(fwd_bwd, cfg["runs"]))
        err = np.abs(project(g, geo, extent=e) - ref)
        pairs, _ = _pairs(g, geo, e)
        rows.append({"extent": e, "fwd_s": tf, "fwdbwd_s": tfb, "pairs": pairs,
                     "max_err_rel": float(err.max() / ref.max()),
                     "mean_err_rel": float(err.mean() / ref.mean()),
                     "mass_fraction_lost": float(np.exp(-0.5 * e * e))})
    return rows


def worker_footprint(cfg):
    """Pixels a conservative bounding-sphere box would visit vs the exact footprint."""
    import numpy as np
    from mi_grg.core.projector import DEFAULT_EXTENT
    g, geo, (x, s, q) = _workload(cfg["n"], cfg["nd"])
    exact, _ = _pairs(g, geo, DEFAULT_EXTENT)
    E = DEFAULT_EXTENT
    a = geo.angles[0]
    src = geo.DSO * np.array([np.cos(a), np.sin(a), 0.0])
    depth = (src - x) @ np.array([np.cos(a), np.sin(a), 0.0])   # along the source->detector axis
    r = E * s.max(1)
    pix = geo.dDetector[0]
    # sphere of radius r seen from the source: image radius <= DSD r / sqrt(d^2 - r^2) (near side)
    dist = np.linalg.norm(x - src, axis=1)
    rad_px = geo.DSD * r / np.sqrt(np.maximum(dist ** 2 - r ** 2, 1e-12)) / pix
    rad_px = rad_px * dist / np.maximum(depth, 1e-12)     # obliquity of off-axis rays
    side = np.minimum(2 * rad_px + 1, geo.nDetector[0])
    return {"exact_pairs": exact, "sphere_box_pairs": float(np.sum(side ** 2)),
            "ratio": float(np.sum(side ** 2) / max(exact, 1))}


def worker_ad_compare(cfg):
    """Alternative design: no hand-written backward. Expand (record, pixel) pairs with a
    prefix sum, gather the record parameters per pair, scatter_add, let Dr.Jit AD
    differentiate it. Same records/footprints as the projector; returns time and RSS."""
    import resource
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    from mi_grg.core import projector as P
    from mi_grg.core import projector_records as R
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector_chunks import PreparedChunk, expand_rows
    from mi_grg.core.projector_kernels import row_interval
    g, geo, _ = _workload(cfg["n"], cfg["nd"])
    fr = P.view_frames(geo)
    det = R.DetectorConstants(fr, geo, P.DEFAULT_EXTENT)
    views = R.ViewFrameArrays(fr)
    nv, nu = geo.nDetector
    y = mi.Float(np.random.default_rng(1).normal(size=nv * nu).astype(np.float32))

    def run():
        leaves = [type(a)(a) for a in (g.positions, g.scales, g.rotations, g.densities)]
        for a in leaves:
            dr.enable_grad(a)
        gauss = R.gaussian_arrays(Gaussians(*leaves), None)
        with dr.suspend_grad():
            prep = PreparedChunk(gauss, views, det, 0, 1, 0, len(g), None, len(g))
        frame = R.RecordFrame(gauss, views, det, prep.reg_gi, prep.reg_vi)
        params = R.regular_params(frame, det)
        with dr.suspend_grad():
            footprint = R.footprint_ellipse({k: dr.detach(v) for k, v in params.items()}, det)
            rows = footprint["n_rows"].numpy()
        image = dr.zeros(mi.Float, nv * nu)
        for rec, row in expand_rows(rows, footprint["row_lo"], P.ROWS_PER_BATCH):
            with dr.suspend_grad():
                uc = dr.gather(mi.Float, dr.detach(params["uc"]), rec)
                vc = dr.gather(mi.Float, dr.detach(params["vc"]), rec)
                lo, hi = row_interval(det, uc, mi.Float(row) + 0.5 - vc, footprint, rec)
                cnt = mi.UInt32(dr.maximum(hi - lo + 1, 0))
                off = dr.prefix_sum(cnt)
                total = int(dr.sum(mi.Float(cnt), axis=None)[0])
                mark = dr.zeros(mi.UInt32, total)
                idx = dr.compress(cnt > 0)
                dr.scatter(mark, 1, dr.gather(mi.UInt32, off, idx))
                lane = dr.gather(mi.UInt32, idx, dr.cumsum(mark) - 1)   # (record,row) of pair
                j = mi.Int32(dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, off, lane)) \
                    + dr.gather(mi.Int32, lo, lane)
                r = dr.gather(mi.UInt32, rec, lane)
                v = mi.Float(dr.gather(mi.Int32, row, lane)) + 0.5
                u = mi.Float(j) + 0.5
            t = {k: dr.gather(mi.Float, params[k], r) for k in params}
            du, dv = u - t["uc"], v - t["vc"]
            y1 = t["N11"] * du + t["N21"] * dv
            y2 = t["N22"] * dv
            pu, pv = du - t["su"], dv - t["sv"]
            z1 = t["D11"] * pu + t["D21"] * pv
            z2 = t["D22"] * pv
            den = 1 + z1 * z1 + z2 * z2
            m2 = (y1 * y1 + y2 * y2) / den
            su_len = det.a_u + u * det.du
            sv_len = det.a_v + v * det.dv
            L = dr.sqrt(det.h2 + su_len * su_len + sv_len * sv_len)
            val = t["amp"] * L * dr.rsqrt(den) * dr.exp(-0.5 * dr.minimum(m2, det.E2))
            dr.scatter_add(image, val, mi.UInt32(mi.Int32(v - 0.5) * nu + j), active=m2 <= det.E2)
        dr.backward(dr.sum(image * y))
        dr.eval([dr.grad(a) for a in leaves])

    run()
    times = _timed(run, cfg["runs"])
    return {"ad_fwdbwd_s": statistics.median(times),
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2}


WORKERS = {"grid": worker_grid, "phases": worker_phases, "extent": worker_extent,
           "footprint": worker_footprint, "ad_compare": worker_ad_compare}


# ====================================================================== driver side
def _spawn(kind, cfg, **env_extra):
    env = dict(os.environ, **env_extra)      # MI_GRG_VARIANT: set by main from --variant
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, json.dumps(cfg)]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(ROOT))
    if res.returncode != 0:
        raise RuntimeError(f"worker {kind} {cfg} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _fmt(x, unit=""):
    return f"{x:.3g}{unit}"


def _markdown(res) -> str:
    g = res["grid"]
    lines = ["# Projector benchmark (`bench/projector.py`)", "",
             f"Machine: {res['machine']}. Variant {res.get('variant', 'llvm_ad_mono')}. Date {res['date']}. "
             f"Mode: {'quick' if res['quick'] else 'full'}; medians of {res['runs']} runs "
             "after one warm-up call.", "",
             "Workload: N Gaussians uniform in the unit ball, scale = 0.5 x mean 3-NN distance "
             "x log-normal(0.3) per axis, random rotations; ONE cone-beam view (DSO 5, DSD 7, "
             "3.2 x 3.2 detector). Pairs = (Gaussian, pixel) evaluations (exact footprints, "
             f"extent {res['extent']}). Forward+backward = project_dr + dr.backward of "
             "<image, y> for positions, scales, rotations, densities and means2d.", "",
             "| N | detector | pairs / view | fwd s/view (min) | fwd Mpairs/s | fwd+bwd s/view (min) "
             "| fwd+bwd Mpairs/s | first call fwd / fwd+bwd s | peak RSS GB |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in g:
        lines.append(
            f"| {r['n']:,} | {r['nd']}^2 | {r['pairs'] / 1e6:.1f} M | {r['fwd_s']:.3f} "
            f"({min(r['fwd_runs']):.3f}) | {r['pairs'] / r['fwd_s'] / 1e6:.0f} | "
            f"{r['fwdbwd_s']:.3f} ({min(r['fwdbwd_runs']):.3f}) | "
            f"{r['pairs'] / r['fwdbwd_s'] / 1e6:.0f} | {r['first_fwd_s']:.2f} / "
            f"{r['first_fwdbwd_s']:.2f} | {r['peak_rss_gb']:.2f} |")
    lines += ["", "Times are medians (minimum in brackets); Mpairs/s from the medians."]
    t = res["targets"]
    lines += ["", "## Targets", "", "| target | required | measured | met |", "|---|---|---|---|"]
    for row in t:
        lines.append(f"| {row['name']} | {row['required']} | {row['measured']} | "
                     f"{'yes' if row['met'] else '**no**'} |")
    if res.get("multiview"):
        m = res["multiview"]
        lines += ["", f"Multi-view call ({m['views']} views in one call, N = {m['n']:,}, "
                  f"{m['nd']}^2): fwd {m['fwd_s'] / m['views']:.3f} s/view "
                  f"({m['pairs'] / m['fwd_s'] / 1e6:.0f} Mpairs/s), fwd+bwd "
                  f"{m['fwdbwd_s'] / m['views']:.3f} s/view "
                  f"({m['pairs'] / m['fwdbwd_s'] / 1e6:.0f} Mpairs/s), peak RSS "
                  f"{m['peak_rss_gb']:.2f} GB."]
    c = res.get("cold")
    if c:
        lines += ["", f"JIT compilation (empty kernel cache, N = {c['n']:,}, {c['nd']}^2): first "
                  f"forward call {c['first_fwd_s']:.2f} s, first forward+backward call "
                  f"{c['first_fwdbwd_s']:.2f} s (later calls: {c['fwd_s']:.3f} / "
                  f"{c['fwdbwd_s']:.3f} s)."]
    ph = res.get("phases")
    if ph:
        lines += ["", f"## Where the time goes (N = {res['phases_cfg']['n']:,}, "
                  f"{res['phases_cfg']['nd']}^2, one fwd+bwd, profiled)", "",
                  "| phase | s |", "|---|---|"]
        for k, v in sorted(ph.items(), key=lambda kv: -kv[1]):
            if v >= 5e-4:
                lines.append(f"| {k} | {v:.4f} |")
        lines += ["", "kernel_*: the per-pixel loops; ad_backward: Dr.Jit AD from the 11 record "
                  "parameters to the Gaussians; classify: per-record setup and row expansion; other: the "
                  "rest (arguments, images)."]
    ext = res["extent"]
    lines += ["", "## Accuracy vs time (truncation extent)", "",
              f"N = {res['extent_cfg']['n']:,}, {res['extent_cfg']['nd']}^2, one view; error "
              "vs the same projector at extent 9 (truncation 3e-18; float32 closed form).", "",
              "| extent | exp(-E^2/2) | max err / max | mean err / mean | pairs | fwd s | fwd+bwd s |",
              "|---|---|---|---|---|---|---|"]
    for r in res["extents"]:
        lines.append(f"| {r['extent']} | {r['mass_fraction_lost']:.1e} | {r['max_err_rel']:.1e} | "
                     f"{r['mean_err_rel']:.1e} | {r['pairs'] / 1e6:.1f} M | {r['fwd_s']:.3f} | "
                     f"{r['fwdbwd_s']:.3f} |")
    fp = res.get("footprint")
    if fp:
        lines += ["", "## Footprints", "",
                  f"Exact per-row ellipse footprints visit {fp['exact_pairs'] / 1e6:.1f} M pixels; "
                  "the conservative bounding-sphere box (radius extent x max scale, near side, "
                  f"clamped) would visit {fp['sphere_box_pairs'] / 1e6:.1f} M "
                  f"({fp['ratio']:.1f}x) for the same workload (N = {res['footprint_cfg']['n']:,}, "
                  f"{res['footprint_cfg']['nd']}^2)."]
    ad = res.get("ad_compare")
    if ad:
        base = next((r for r in g if r["n"] == res["ad_cfg"]["n"] and r["nd"] == res["ad_cfg"]["nd"]), None)
        lines += ["", "## Design choice: hand-written backward vs Dr.Jit AD", "",
                  "Alternative measured in the same run: flat (record, pixel) pair arrays from a "
                  "prefix sum, per-pair gathers of the record parameters, scatter_add, "
                  "differentiated by Dr.Jit AD (symbolic loops cannot be reverse-differentiated).",
                  "", f"N = {res['ad_cfg']['n']:,}, {res['ad_cfg']['nd']}^2, fwd+bwd: AD "
                  f"{ad['ad_fwdbwd_s']:.3f} s, peak RSS {ad['peak_rss_gb']:.2f} GB"
                  + (f"; projector (CustomOp) {base['fwdbwd_s']:.3f} s, peak RSS "
                     f"{base['peak_rss_gb']:.2f} GB." if base else ".")]
    base = max(r.get("baseline_rss_gb", 0.0) for r in g)
    lines += ["", "Notes: the first call includes JIT compilation or loading compiled kernels "
              "from Dr.Jit's on-disk cache (~/.drjit); later calls reuse them for any N and "
              "geometry (geometry scalars are opaque kernel inputs) with the same image size "
              "(views x nv x nu: ReduceMode.Expand bakes it into the scatter kernels). Peak RSS includes the Python "
              f"interpreter, Mitsuba and Dr.Jit ({base:.2f} GB after the imports). "
              f"Load average when the run ended: {res.get('loadavg', '?')} (2 cores; other "
              "jobs on the machine inflate times)."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--runs", type=int, default=None, help="timed runs per config (>= 3)")
    ap.add_argument("--out", default=None,
                    help="output folder (default docs/bench; --quick: a temporary folder)")
    ap.add_argument("--variant", default="llvm_ad_mono", choices=("llvm_ad_mono", "cuda_ad_mono"))
    ap.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        sys.path.insert(0, str(ROOT))
        import mi_grg  # noqa: F401  (before drjit: selects the LLVM library)
        out = WORKERS[a.worker[0]](json.loads(a.worker[1]))
        print(json.dumps(out))
        return 0
    os.environ["MI_GRG_VARIANT"] = a.variant   # the driver's: inherited by every worker
    from mi_grg.core.projector import DEFAULT_EXTENT  # noqa: F401 (also checks the import)
    runs = max(3, a.runs or 3)
    if a.quick:
        ns, nds = [10_000], [128]
        ext_cfg = {"n": 10_000, "nd": 128, "extents": [3.0, 4.0, DEFAULT_EXTENT, 5.0], "runs": runs}
        ph_cfg = fp_cfg = ad_cfg = {"n": 10_000, "nd": 128, "runs": runs}
    else:
        ns, nds = [10_000, 50_000, 200_000], [128, 256, 512]
        ext_cfg = {"n": 50_000, "nd": 256, "extents": [3.0, 4.0, DEFAULT_EXTENT, 5.0], "runs": runs}
        ph_cfg = fp_cfg = ad_cfg = {"n": 50_000, "nd": 256, "runs": runs}
    grid = []
    for n in ns:
        for nd in nds:
            r = _spawn("grid", {"n": n, "nd": nd, "runs": runs})
            print(f"N={n:>7} {nd:>4}^2: pairs {r['pairs'] / 1e6:7.1f} M  fwd {r['fwd_s']:.3f} s "
                  f"({r['pairs'] / r['fwd_s'] / 1e6:5.0f} M/s)  fwd+bwd {r['fwdbwd_s']:.3f} s "
                  f"({r['pairs'] / r['fwdbwd_s'] / 1e6:5.0f} M/s)  peak {r['peak_rss_gb']:.2f} GB",
                  flush=True)
            grid.append(r)
    multi = None if a.quick else _spawn("grid", {"n": 50_000, "nd": 256, "runs": runs, "views": 8})
    # JIT compilation: the same config with an empty kernel cache (Dr.Jit keeps it in $HOME)
    import tempfile
    with tempfile.TemporaryDirectory() as home:
        cold_cfg = {"n": ns[0], "nd": nds[0], "runs": runs}
        cold = _spawn("grid", cold_cfg, HOME=home)
    phases = _spawn("phases", ph_cfg)
    extents = _spawn("extent", ext_cfg)
    footprint = _spawn("footprint", fp_cfg)
    ad = _spawn("ad_compare", ad_cfg)
    fwd_rate = min(r["pairs"] / r["fwd_s"] for r in grid)
    fb_rate = min(r["pairs"] / r["fwdbwd_s"] for r in grid)
    peak = max([r["peak_rss_gb"] for r in grid] + ([multi["peak_rss_gb"]] if multi else []))
    ref = next((r for r in grid if r["n"] == 50_000 and r["nd"] == 256), None)
    targets = [
        {"name": "forward pairs/s (slowest config)", "required": ">= 60 M/s",
         "measured": f"{fwd_rate / 1e6:.0f} M/s", "met": fwd_rate >= TARGETS["fwd_pairs_per_s"]},
        {"name": "fwd+bwd pairs/s (slowest config)", "required": ">= 20 M/s",
         "measured": f"{fb_rate / 1e6:.0f} M/s", "met": fb_rate >= TARGETS["fwdbwd_pairs_per_s"]},
        {"name": "peak memory (all configs)", "required": "<= 2 GB",
         "measured": f"{peak:.2f} GB", "met": peak <= TARGETS["peak_rss_gb"]}]
    if ref:
        targets.insert(2, {"name": "50k Gaussians x 256^2, fwd+bwd per view", "required": "<= 1 s",
                           "measured": f"{ref['fwdbwd_s']:.3f} s",
                           "met": ref["fwdbwd_s"] <= TARGETS["fwdbwd_50k_256_s"]})
    import platform
    try:
        cpu = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor()
    machine = f"{cpu}, {os.cpu_count()} cores"
    if a.variant.startswith("cuda"):
        try:
            gpu = subprocess.check_output(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                          text=True).strip().splitlines()[0]
        except (OSError, subprocess.CalledProcessError, IndexError):
            gpu = "a CUDA GPU"
        machine = f"{gpu} (host: {machine})"
    res = {"machine": machine, "variant": a.variant, "date": time.strftime("%Y-%m-%d"),
           "quick": a.quick, "runs": runs, "extent": DEFAULT_EXTENT, "grid": grid,
           "multiview": multi, "cold": cold, "phases": phases, "phases_cfg": ph_cfg, "extents": extents,
           "extent_cfg": ext_cfg, "footprint": footprint, "footprint_cfg": fp_cfg,
           "ad_compare": ad, "ad_cfg": ad_cfg, "targets": targets}
    res["loadavg"] = " ".join(f"{x:.1f}" for x in os.getloadavg())
    if a.out:
        out = Path(a.out)
    elif a.quick:
        import tempfile
        out = Path(tempfile.gettempdir()) / "mi_grg_bench"
    else:
        out = ROOT / "docs" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    name = ("projector_quick" if a.quick else "projector") + \
        ("_cuda" if a.variant.startswith("cuda") else "")
    (out / f"{name}.json").write_text(json.dumps(res, indent=1))
    (out / f"{name}.md").write_text(_markdown(res))
    print(_markdown(res))
    print(f"written: {out / (name + '.md')}, {out / (name + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
