"""Per-view scan geometry: quality on half-fan and wobbling scans, and speed of vector scans.

Cases: the default scanner (mi_grg.data.simulate.default_geometry) at n^3, detector 1.5 n,
25 noisy training views (TIGRE CTnoise, I0 1e4, electronic std 10) and 25 test views of
the Shepp-Logan phantom, scanned four ways:

* ``circular``: the centred circle;
* ``half_fan``: the detector offset by 0.3 of its width (360 degrees);
* ``wobbling``: source height +-0.12, detector roll +-2 degrees, DSD +-3 %, varying per
  view (``mi_grg.data.orbits.wobbling``);
* ``wobbling_ignored``: the wobbling scan's projections reconstructed on the nominal
  circle (its vectors dropped), what a reader that ignores them does;
* ``skewed``: the wobbling scan with its detector rows sheared against the columns by
  +-5 degrees per view (``wobbling(..., skew_deg=5)``: a parallelogram pixel grid);
* ``skewed_ignored``: the skewed scan's projections reconstructed with rows at right
  angles (the wobbling scan's vectors), what a reader that squares the grid does.

Methods fdk, pdhg and gr (gr with ``--gr-iterations``, small so that it runs on a loaded
CPU); FDK's half-fan loss by view count, with and without noise; FDK on a short scan (180
degrees plus the fan angle) with and without Parker's weights; FDK's full-circle weight
per view (2 pi / n) against each view's own angular step (RTK's). Speed: the Joseph
projector (A and A^T) and the Gaussian projector (25 views) on the circular scan, the same
scan given as vectors, the wobbling scan and the skewed one (medians of repeats).

    python bench/per_view_geometry.py                     # 32^3, gr 500 iterations
    python bench/per_view_geometry.py --n 64 --gr-iterations 1500
    python bench/per_view_geometry.py --parts short_scan   # only that table, merged
    python bench/per_view_geometry.py --parts quality --scans skewed skewed_ignored
    python bench/per_view_geometry.py --parts view_steps   # FDK: 2 pi / n or each step

Writes docs/bench/per_view_geometry.json and .md.
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

ROOT = Path(__file__).resolve().parents[1]
SCANS = ("circular", "half_fan", "wobbling", "wobbling_ignored", "skewed", "skewed_ignored")
SKEW_DEG = 5.0
PARTS = ("speed", "quality", "fdk_gap", "short_scan", "view_steps")


def cases(n: int) -> dict:
    """The cases (Case objects, ``SCANS``) of one phantom at n^3."""
    import numpy as np
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.orbits import half_fan, wobbling
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=n, det=int(1.5 * n), views=25)
    test = default_test_angles(25)
    allv = wobbling(geo.with_angles(np.concatenate([geo.angles, test])),
                    height=0.12, roll_deg=2.0, dsd=0.03)
    out = {"circular": simulate_case("shepp", geo, test, NoiseModel(), seed=0),
           "half_fan": simulate_case("shepp", half_fan(geo, 0.3), test, NoiseModel(), seed=0),
           "wobbling": simulate_case("shepp", allv.with_angles(geo.angles), test,
                                     NoiseModel(), seed=0)}
    sheared = wobbling(geo.with_angles(np.concatenate([geo.angles, test])),
                       height=0.12, roll_deg=2.0, dsd=0.03, skew_deg=SKEW_DEG)
    out["skewed"] = simulate_case("shepp", sheared.with_angles(geo.angles), test,
                                  NoiseModel(), seed=0)

    def regeometry(case, geometry):
        return type(case)(geometry=geometry, train=case.train, test_angles=case.test_angles,
                          test=case.test, vol_gt=case.vol_gt, info=case.info)
    out["wobbling_ignored"] = regeometry(out["wobbling"], out["wobbling"].geometry.circular())
    out["skewed_ignored"] = regeometry(out["skewed"], out["wobbling"].geometry)
    return {k: out[k] for k in SCANS}


def quality(n: int, gr_iterations: int, methods, scans=SCANS) -> list:
    import mi_grg
    rows = []
    for scan, case in cases(n).items():
        if scan not in scans:
            continue
        for method in methods:
            opts = {} if method == "fdk" else {"progress": False}
            if method == "gr":
                opts["iterations"] = gr_iterations
            t0 = time.perf_counter()
            _, m = mi_grg.reconstruct(case, method, **opts)
            rows.append({"scan": scan, "method": method, "psnr_3d": m["psnr_3d"],
                         "ssim_3d": m["ssim_3d"], "seconds": time.perf_counter() - t0})
            print(f"{scan:17s} {method:5s} PSNR {m['psnr_3d']:.2f} dB  "
                  f"({rows[-1]['seconds']:.0f} s)", flush=True)
    return rows


def fdk_gap(n: int, views=(25, 50, 100, 360)) -> list:
    """FDK's half-fan loss against the centred circle by view count, with the bench's noise
    and without it (I0 1e12): where the loss comes from (FDK's weights are Wang's, equal to
    RTK's displaced-detector FDK: tests/test_per_view.py)."""
    import mi_grg
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.orbits import half_fan
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    rows = []
    for nv in views:
        geo = default_geometry(n=n, det=int(1.5 * n), views=nv)
        for noise, model in (("noisy", NoiseModel()),
                             ("clean", NoiseModel(I0=1e12, electronic_std=0.0))):
            p = {scan: mi_grg.reconstruct(simulate_case("shepp", g, default_test_angles(5),
                                                        model, seed=0), "fdk")[1]["psnr_3d"]
                 for scan, g in (("circular", geo), ("half_fan", half_fan(geo, 0.3)))}
            rows.append({"views": nv, "noise": noise, **p})
            print(f"fdk {nv} views {noise}: half-fan {p['half_fan'] - p['circular']:+.2f} dB",
                  flush=True)
    return rows


def short_scan(n: int, views=(25, 100)) -> list:
    """FDK on the centred circle and on a short scan of 180 degrees plus the fan angle (the
    same number of views), the short scan with Parker's weights and without them (what FDK
    did before it had them), noisy and clean."""
    import numpy as np
    import mi_grg
    from mi_grg.core import fdk_geometry
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    rows = []
    for nv in views:
        geo = default_geometry(n=n, det=int(1.5 * n), views=nv)
        fan = 2 * np.arctan(0.5 * geo.sDetector[1] / geo.DSD)
        short = geo.with_angles(np.linspace(0.0, np.pi + fan, nv))
        for noise, model in (("noisy", NoiseModel()),
                             ("clean", NoiseModel(I0=1e12, electronic_std=0.0))):
            def score(g):
                case = simulate_case("shepp", g, default_test_angles(5), model, seed=0)
                return mi_grg.reconstruct(case, "fdk")[1]["psnr_3d"]
            row = {"views": nv, "noise": noise, "span_deg": float(np.degrees(np.pi + fan)),
                   "circular": score(geo), "short_parker": score(short)}
            weights = fdk_geometry.short_scan_weights
            fdk_geometry.short_scan_weights = lambda g: None
            try:
                row["short_unweighted"] = score(short)
            finally:
                fdk_geometry.short_scan_weights = weights
            rows.append(row)
            print(f"fdk short scan {nv} views {noise}: Parker "
                  f"{row['short_parker'] - row['circular']:+.2f} dB, unweighted "
                  f"{row['short_unweighted'] - row['circular']:+.2f} dB", flush=True)
    return rows


def view_steps(n: int) -> list:
    """FDK's full-circle weight per view, 2 pi / n (ours) against each view's own angular
    step (RTK's), on 25-view circles with views left out (as a held-out split leaves them)
    and on circles whose per-view azimuths deviate from the nominal ones; noisy."""
    import numpy as np
    import mi_grg
    from mi_grg.core import fdk_geometry
    from mi_grg.core.view_vectors import circular_vectors
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    parker = fdk_geometry.short_scan_weights

    def with_view_steps(g):
        """Each view's step (half the arc to its two neighbours) over 2 pi / n, [view, nu];
        a short scan keeps Parker's weights."""
        w = parker(g)
        if w is not None:
            return w
        steps = fdk_geometry.view_steps(fdk_geometry.view_angles(g))
        return np.repeat(steps[:, None], g.nDetector[1], 1)

    geo = default_geometry(n=n, det=int(1.5 * n), views=25)
    scans = []
    for drop in ([0], [0, 12], [0, 8, 16, 24], [0, 5, 10, 15, 20]):
        keep = [i for i in range(25) if i not in drop]
        scans.append((f"circle, views {drop} left out", geo.with_angles(geo.angles[keep])))
    test = default_test_angles(5)
    both = geo.with_angles(np.concatenate([geo.angles, test]))
    for jitter in (1.5, 4.0):
        for seed in range(3):
            a = both.angles + np.radians(np.concatenate([
                np.random.default_rng(seed).uniform(-jitter, jitter, 25), np.zeros(test.size)]))
            rows = np.stack(np.broadcast_arrays(*circular_vectors(
                np.cos(a), np.sin(a), geo.DSD, geo.DSO, geo.dDetector, geo.offDetector)), -1)
            scans.append((f"azimuths +-{jitter} deg, seed {seed}",
                          both.replace(vectors=rows).with_angles(geo.angles)))
    out = []
    for name, g in scans:
        case = simulate_case("shepp", g, test, NoiseModel(), seed=0)
        row = {"scan": name, "views": g.n_views,
               "two_pi_over_n": mi_grg.reconstruct(case, "fdk")[1]["psnr_3d"]}
        fdk_geometry.short_scan_weights = with_view_steps
        try:
            row["view_steps"] = mi_grg.reconstruct(case, "fdk")[1]["psnr_3d"]
        finally:
            fdk_geometry.short_scan_weights = parker
        out.append(row)
        print(f"fdk {name}: view steps {row['view_steps'] - row['two_pi_over_n']:+.3f} dB",
              flush=True)
    return out



def _median_time(fn, reps: int) -> float:
    import drjit as dr
    fn()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        dr.eval(fn())
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def speed(n: int, reps: int) -> list:
    import mitsuba as mi
    import numpy as np
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.joseph import JosephProjector
    from mi_grg.core.projector import project_dr
    from mi_grg.data.orbits import wobbling
    from mi_grg.data.simulate import default_geometry
    geo = default_geometry(n=n, det=int(1.5 * n), views=25)
    rng = np.random.default_rng(0)
    q = rng.normal(size=(20000, 4))
    g = Gaussians.from_numpy(rng.uniform(-0.6, 0.6, (20000, 3)),
                             rng.uniform(0.01, 0.05, (20000, 3)),
                             q / np.linalg.norm(q, axis=1, keepdims=True),
                             rng.uniform(0.5, 2.0, 20000))
    rows = []
    for name, gg in (("circular", geo), ("circular_as_vectors", geo.as_vectors()),
                     ("wobbling", wobbling(geo)), ("skewed", wobbling(geo, skew_deg=SKEW_DEG))):
        A = JosephProjector(gg)
        x = mi.Float(rng.uniform(0, 1, A.n_vox).astype(np.float32))
        y = mi.Float(rng.uniform(0, 1, gg.n_views * A.n_pix).astype(np.float32))
        rows.append({"scan": name,
                     "joseph_forward_s": _median_time(lambda: A.forward(x, gg.angles), reps),
                     "joseph_adjoint_s": _median_time(lambda: A.adjoint(y, gg.angles), reps),
                     "gaussian_25_views_s": _median_time(lambda: project_dr(g, gg), reps),
                     "gaussian_1_view_s": _median_time(
                         lambda: project_dr(g, gg.with_angles(gg.angles[:1])), reps)})
        print(rows[-1], flush=True)
    return rows


def markdown(res: dict) -> str:
    q = {(r["scan"], r["method"]): r["psnr_3d"] for r in res.get("quality", [])}
    methods = sorted({m for _, m in q}, key=["fdk", "pdhg", "gr"].index)
    out = [f"# Per-view geometry ({res['n']}^3, 25 noisy views, gr {res.get('gr_iterations')} "
           "iterations)", "", "Written by `bench/per_view_geometry.py`; "
           f"{res['machine']}."]
    if q:
        out += ["", "## Quality (3-D PSNR, dB; in brackets: minus the circular scan)", "",
                "| scan | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for scan in SCANS if q else ():
        cells = []
        for m in methods:
            v, c = q.get((scan, m)), q.get(("circular", m))
            cells.append("-" if v is None else f"{v:.2f} ({v - c:+.2f})")
        out.append(f"| {scan} | " + " | ".join(cells) + " |")
    if res.get("fdk_gap"):
        out += ["", f"## FDK's half-fan loss by view count ({res['n']}^3, Shepp-Logan; dB, "
                "half-fan minus circular)", "", "| views | noisy (the bench's noise) | "
                "clean (I0 1e12) |", "|---|---|---|"]
        gap = {(r["views"], r["noise"]): r["half_fan"] - r["circular"]
               for r in res["fdk_gap"]}
        for nv in sorted({r["views"] for r in res["fdk_gap"]}):
            out.append(f"| {nv} | {gap[(nv, 'noisy')]:+.2f} | {gap[(nv, 'clean')]:+.2f} |")
    if res.get("short_scan"):
        r0 = res["short_scan"][0]
        out += ["", f"## FDK on a short scan ({res['n']}^3, Shepp-Logan, {r0['span_deg']:.0f} "
                "degrees, the same number of views as the circle; 3-D PSNR dB)", "",
                "| views | noise | circle | short scan, Parker's weights | short scan, unweighted |",
                "|---|---|---|---|---|"]
        for r in res["short_scan"]:
            out.append(f"| {r['views']} | {r['noise']} | {r['circular']:.2f} | "
                       f"{r['short_parker']:.2f} ({r['short_parker'] - r['circular']:+.2f}) | "
                       f"{r['short_unweighted']:.2f} ({r['short_unweighted'] - r['circular']:+.2f}) |")
    if res.get("view_steps"):
        out += ["", f"## FDK's weight per view on a full circle ({res['n']}^3, Shepp-Logan, "
                "noisy; 3-D PSNR dB)", "", "| scan | views | 2 pi / n (ours) | each view's "
                "step (RTK's) |", "|---|---|---|---|"]
        for r in res["view_steps"]:
            out.append(f"| {r['scan']} | {r['views']} | {r['two_pi_over_n']:.2f} | "
                       f"{r['view_steps']:.2f} ({r['view_steps'] - r['two_pi_over_n']:+.2f}) |")
    if res.get("speed"):
        out += ["", "## Speed (median seconds)", "", "| scan | Joseph A | Joseph A^T | "
                "Gaussians, 25 views | Gaussians, 1 view |", "|---|---|---|---|---|"]
        base = res["speed"][0]
        for r in res["speed"]:
            cells = [f"{r[k]:.4f} ({r[k] / base[k]:.2f}x)" for k in
                     ("joseph_forward_s", "joseph_adjoint_s", "gaussian_25_views_s",
                      "gaussian_1_view_s")]
            out.append(f"| {r['scan']} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--speed-n", type=int, default=64)
    ap.add_argument("--gr-iterations", type=int, default=500)
    ap.add_argument("--methods", nargs="+", default=["fdk", "pdhg", "gr"])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS),
                    help="what to measure; the others are kept from an existing JSON")
    ap.add_argument("--scans", nargs="+", choices=SCANS, default=list(SCANS),
                    help="the quality part's scans; the other scans' rows are kept")
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "per_view_geometry"))
    args = ap.parse_args(argv)
    import mi_grg  # noqa: F401  (first: Dr.Jit's LLVM library)
    out = Path(args.out)
    res = {}
    partial = set(args.parts) != set(PARTS) or set(args.scans) != set(SCANS)
    if partial and out.with_suffix(".json").is_file():
        res = json.loads(out.with_suffix(".json").read_text())
        if res.get("n") != args.n:
            ap.error(f"--n {args.n} differs from the existing {out}.json's n = {res.get('n')}")
    res.update({"n": args.n, "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
                f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start"})
    if "speed" in args.parts:
        res.update(speed_n=args.speed_n, speed=speed(args.speed_n, args.reps))
    if "quality" in args.parts:
        if res.get("quality") and set(args.scans) != set(SCANS) \
                and res.get("gr_iterations") != args.gr_iterations:
            ap.error(f"--gr-iterations {args.gr_iterations} differs from the kept rows' "
                     f"{res.get('gr_iterations')}")
        kept = [r for r in res.get("quality", []) if r["scan"] not in args.scans]
        res.update(gr_iterations=args.gr_iterations,
                   quality=kept + quality(args.n, args.gr_iterations, args.methods, args.scans))
    if "fdk_gap" in args.parts:
        res["fdk_gap"] = fdk_gap(args.n)
    if "short_scan" in args.parts:
        res["short_scan"] = short_scan(args.n)
    if "view_steps" in args.parts:
        res["view_steps"] = view_steps(args.n)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=2))
    out.with_suffix(".md").write_text(markdown(res))
    print(f"wrote {out}.json, {out}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
