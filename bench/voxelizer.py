"""Voxelizer timings: 128^3 and 256^3 from 50k Gaussians, a 32^3 training block, 256^3 from 1M.

Usage:  .venv/bin/python bench/voxelizer.py [--repeats 5] [--large] [--out docs/bench/voxelizer.md]
        .venv/bin/python bench/voxelizer.py --cases 1m --repeats 3 --update   # one case

Gaussians resemble R2-Gaussian's initialisation of a real object: 50k centres uniform in a
ball of radius 0.85 inside the [-1, 1]^3 volume (the object fills ~1/3 of the cube),
scale = root mean square distance to the 3 nearest centres (R2-Gaussian's rule), times a
random anisotropy exp(U(-0.3, 0.3)) per axis, random rotations, densities U(0.01, 0.2).
That gives a mean scale of ~1.8 voxels at 128^3. Times are medians of ``--repeats`` runs
after one warm-up run (kernels compiled and cached), wall clock including the host sync;
peak RSS per case from the kernel's VmHWM counter, reset before each case.
Target (issue "Radiative Gaussians"): 128^3 from 50k Gaussians in <= 0.5 s on this CPU.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import mi_grg
import drjit as dr
import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry
from mi_grg.core.voxelizer import DEFAULT_EXTENT, pair_count, voxelize, voxelize_dr

TARGET_128 = 0.5   # seconds


def init_like_gaussians(n: int, seed: int = 0) -> Gaussians:
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (4 * n, 3))   # ~32 % fall in the ball
    x = x[np.linalg.norm(x, axis=1) < 0.85][:n]
    d, _ = cKDTree(x).query(x, k=4)
    s = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))
    scales = s[:, None] * np.exp(rng.uniform(-0.3, 0.3, (n, 3)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians.from_numpy(x, scales, q, rng.uniform(0.01, 0.2, n))


def geometry(n: int) -> Geometry:
    return Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(64, 64), sDetector=(4.0, 4.0),
                    nVoxel=(n, n, n), sVoxel=(2.0, 2.0, 2.0), angles=[0.0])


def timed(fn, repeats: int) -> dict:
    fn()   # warm-up: kernel compilation
    times = []
    for _ in range(repeats):
        dr.sync_thread()
        t = time.perf_counter()
        fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return {"median_s": statistics.median(times), "min_s": min(times), "runs": len(times)}


def backward_block(g: Gaussians, geo: Geometry, block):
    """Forward + reverse pass of a block regulariser (sum of squares) w.r.t. all arrays."""
    pos, sc, rot, dens = (type(a)(a) for a in (g.positions, g.scales, g.rotations,
                                               g.densities))
    gg = Gaussians(pos, sc, rot, dens)
    dr.enable_grad(pos, sc, rot, dens)
    vol = voxelize_dr(gg, geo, block=block)
    dr.backward(dr.sum(dr.square(vol.array)))
    dr.eval(dr.grad(pos), dr.grad(sc), dr.grad(rot), dr.grad(dens))


#: case key -> row name; DEFAULT_CASES run unless --cases says otherwise
CASES = {"128": "128^3, 50k Gaussians", "256": "256^3, 50k Gaussians",
         "block": "32^3 block of 128^3, 50k Gaussians",
         "block_bwd": "32^3 block, forward + backward", "1m": "256^3, 10^6 Gaussians"}
DEFAULT_CASES = ("128", "256", "block", "block_bwd")
HEADER = ["| case | median (s) | min (s) | pairs (M) | box pairs (M) | M pairs/s | peak RSS (GB) |",
          "|---|---:|---:|---:|---:|---:|---:|"]
RSS_NOTE = ("`peak RSS` = the process's peak resident memory while the case ran (Linux "
            "VmHWM, reset before its warm-up run): it includes Python, Mitsuba/LLVM and the "
            "Gaussians, not just the voxelizer's arrays.")


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process: per-case peaks."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_gb() -> float:
    """VmHWM (peak RSS since the last reset) in GB; ru_maxrss (process peak) if absent."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def table_row(r: dict) -> str:
    rss = f"{r['peak_rss_gb']:.2f}" if r.get("peak_rss_gb") is not None else "—"
    return (f"| {r['name']} | {r['median_s']:.3f} | {r['min_s']:.3f} | "
            f"{r['pairs'] / 1e6:.1f} | {r['box_pairs'] / 1e6:.1f} | "
            f"{r['mpairs_per_s']:.0f} | {rss} |")


def merge_into(text: str, rows: list, note: str) -> str:
    """Put ``rows`` into the table of an existing report (replacing rows of the same case,
    adding a peak-RSS column to older tables as "—") and add ``note`` below the table:
    measuring one case does not mean rerunning all of them."""
    lines = text.rstrip("\n").split("\n")
    head = next(i for i, line in enumerate(lines) if line.startswith("| case |"))
    end = head + 2
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    old_cols = [c.strip() for c in lines[head].strip("|").split("|")]
    new_cols = [c.strip() for c in HEADER[0].strip("|").split("|")]
    body = []
    for line in lines[head + 2:end]:
        cells = dict(zip(old_cols, (c.strip() for c in line.strip("|").split("|"))))
        body.append("| " + " | ".join(cells.get(c, "—") for c in new_cols) + " |")
    for r in rows:
        new = table_row(r)
        idx = [i for i, line in enumerate(body) if line.startswith(f"| {r['name']} |")]
        if idx:
            body[idx[0]] = new
        else:
            body.append(new)
    tail = lines[end:]
    notes = [note] if RSS_NOTE in text else [note, "", RSS_NOTE]
    return "\n".join(lines[:head] + HEADER + body + [""] + notes + tail) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES),
                    help="comma-separated subset of " + ", ".join(
                        f"{k} ({v})" for k, v in CASES.items()))
    ap.add_argument("--large", action="store_true",
                    help="also 10^6 Gaussians into 256^3 (= adding 1m to --cases; slow)")
    ap.add_argument("--update", action="store_true",
                    help="merge the measured rows into the existing --out report instead of "
                         "rewriting it (to measure one case without rerunning the others)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" /
                                         "bench" / "voxelizer.md"))
    args = ap.parse_args(argv)
    if args.repeats < 3:
        ap.error("--repeats must be >= 3 (medians)")
    keys = [k.strip() for k in args.cases.split(",") if k.strip()]
    if args.large and "1m" not in keys:
        keys.append("1m")
    unknown = [k for k in keys if k not in CASES]
    if unknown or not keys:
        ap.error(f"--cases: unknown {unknown}; choose from {list(CASES)}")
    out = Path(args.out)
    if args.update and not out.exists():
        ap.error(f"--update needs an existing report, {out} is missing")
    load_before = os.getloadavg()
    g50 = init_like_gaussians(50_000) if set(keys) - {"1m"} else None
    rows = []
    rss_reset = True

    def case(key, n_gauss, g, geo, fn, block=None):
        nonlocal rss_reset
        name = CASES[key]
        counts = pair_count(g, geo, block=block)
        rss_reset &= reset_peak_rss()
        r = timed(fn, args.repeats)
        r.update(name=name, gaussians=n_gauss, pairs=counts["pairs"],
                 box_pairs=counts["box_pairs"],
                 mpairs_per_s=counts["pairs"] / r["median_s"] / 1e6, peak_rss_gb=peak_rss_gb())
        rows.append(r)
        print(f"{name:42s} {r['median_s']:8.3f} s  (min {r['min_s']:.3f})  "
              f"{counts['pairs'] / 1e6:8.1f} M pairs  {r['mpairs_per_s']:7.1f} M pairs/s  "
              f"peak RSS {r['peak_rss_gb']:.2f} GB", flush=True)

    g128, g256 = geometry(128), geometry(256)
    block = ((48, 48, 48), (32, 32, 32))
    for key in CASES:   # a fixed order, whatever the order of --cases
        if key not in keys:
            continue
        if key == "128":
            case(key, 50_000, g50, g128, lambda: voxelize(g50, g128))
        elif key == "256":
            case(key, 50_000, g50, g256, lambda: voxelize(g50, g256))
        elif key == "block":
            case(key, 50_000, g50, g128, lambda: voxelize(g50, g128, block=block), block=block)
        elif key == "block_bwd":
            case(key, 50_000, g50, g128, lambda: backward_block(g50, g128, block), block=block)
        elif key == "1m":
            g1m = init_like_gaussians(1_000_000, seed=1)
            case(key, 1_000_000, g1m, g256, lambda: voxelize(g1m, g256))
    load_after = os.getloadavg()

    r128 = next((r for r in rows if r["name"] == CASES["128"]), None)
    if r128 is not None:
        t128 = r128["median_s"]
        verdict = "meets" if t128 <= TARGET_128 else "MISSES"
        print(f"\n128^3 / 50k: {t128:.3f} s = {t128 / TARGET_128:.2f} x the {TARGET_128} s "
              f"target ({verdict} it)")
    cpu = platform.processor() or "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    if not rss_reset:
        print("warning: could not reset VmHWM; peak RSS is the process peak so far")
    command = " ".join([Path(sys.argv[0]).name] + (argv if argv is not None else sys.argv[1:]))
    stamp = datetime.datetime.now().isoformat(timespec="seconds")
    if args.update:
        note = (f"Row(s) {', '.join(r['name'] for r in rows)}: measured {stamp} by "
                f"`{command}` alone (the other rows were not rerun); medians of "
                f"{args.repeats} runs after one warm-up run. Machine: {cpu}, "
                f"{os.cpu_count()} cores, shared with other jobs (load average before/after "
                f"{load_before[0]:.2f} / {load_after[0]:.2f}), so times are upper bounds.")
        out.write_text(merge_into(out.read_text(), rows, note))
        print(f"updated {out}")
        return 0
    s = g50.numpy()["scales"] if g50 is not None else None
    lines = [
        "# Voxelizer benchmark (`bench/voxelizer.py`)", "",
        f"Generated {stamp} by `{command}`.", "",
        f"Machine: {cpu}, {os.cpu_count()} cores; variant {mi.variant()}; "
        f"Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}. Load average before/after: "
        f"{load_before[0]:.2f} / {load_after[0]:.2f} (other jobs share these cores, so "
        "times are upper bounds).", "",
        "Gaussians: R2-Gaussian-like initialisation (centres uniform in a ball of radius "
        "0.85 in [-1, 1]^3, scale = RMS distance to the 3 nearest centres x exp(U(-0.3, "
        "0.3)) per axis, random rotations)."
        + (f" 50k Gaussians: mean scale {s.mean():.4f} = {s.mean() / (2 / 128):.2f} voxels "
           "at 128^3." if s is not None else "")
        + f" Truncation extent {DEFAULT_EXTENT} (Mahalanobis). `pairs` = (Gaussian, voxel) "
        "pairs evaluated (inside the ellipsoids' exact z-ranges); `box pairs` = their "
        "bounding boxes. " + RSS_NOTE, "",
        f"Medians of {args.repeats} runs after one warm-up run.", ""] + HEADER
    lines += [table_row(r) for r in rows]
    if r128 is not None:
        lines += ["", f"Target: 128^3 from 50k Gaussians <= {TARGET_128} s: measured "
                  f"{t128:.3f} s, {t128 / TARGET_128:.2f} x the target ({verdict} it)."]
    lines.append("")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
