"""The LLVM kernels with and without packets, in one process, on a late-training state.

    .venv/bin/python bench/packets.py            # gr 64^3 state of bench/train_step.py
    .venv/bin/python bench/packets.py --reps 1   # quicker

Packets (``mi_grg.core.lanes.use_packets``, LLVM only): the projector's primal pass adds
PACKET pixels of a row per store, the backward adds a lane's sums to its record with one
store, each lane reads its record with one packet load; the voxelizer's column lanes add
PACKET voxels along z per store and read their Gaussian from a packed array. The code
keeps the per-pixel / per-voxel path (CUDA's), so both are timed here on the same state,
the configurations interleaved view by view (block by block), so that they see the same
machine load:

* projector, one view with the trainer's extent, forward and forward + backward (to the
  raw parameters): ``per-pixel`` (no packets), ``packets`` (all, PACKET as set),
  ``packets, sums per parameter`` (the backward's sums scatter-added one parameter at a
  time), ``packets, PACKET=8``;
* voxelizer, a 32^3 block at extent 3 and its TV loss (the trainer's TV term), forward and
  forward + backward: ``per-voxel``, ``packets``, ``packets, gathered values`` (no packed
  Gaussian array), ``packets, PACKET=8``.

State: ``out/bench_cache/train_state_gr_64.npz`` (made by bench/train_step.py on first
use). Writes docs/bench/packets.{md,json}: wall and CPU ms, medians over views / blocks.
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
sys.path.insert(0, str(ROOT / "bench"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3, help="passes over the 13 views / 10 blocks")
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench"))
    args = ap.parse_args(argv)
    import train_step
    if not train_step.state_path("gr", 64).exists():
        train_step._spawn(["--make-state", "gr", "64", str(train_step.TRAIN_ITERS[64])])
    import mi_grg  # noqa: F401  (first: Dr.Jit's LLVM library and the variant)
    import numpy as np
    import drjit as dr
    from mi_grg.core import lanes as L
    from mi_grg.core import projector as P
    from mi_grg.core import voxelizer as V
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.data.simulate import default_geometry
    from mi_grg.training.losses import tv_3d
    if not L.use_packets():
        raise SystemExit("packets are the LLVM backend's path: run with llvm_ad_mono")
    raw, _ = train_step._load_state("gr", 64)
    geo = default_geometry(n=64, det=96, views=25)
    extent = train_step._train_extent()
    # the projector's modules read lanes.use_packets / PACKET at call time; the voxelizer
    # holds its own PACKET and _use_packets; EXPAND_BYTES is shared by both
    saved = {"packets": L.use_packets, "expand": L.EXPAND_BYTES, "packet": L.PACKET,
             "use": V._use_packets, "pack": V._pack_chunk, "vpacket": V.PACKET}

    def restore():
        L.use_packets, L.EXPAND_BYTES, L.PACKET = saved["packets"], saved["expand"], saved["packet"]
        V._use_packets, V._pack_chunk, V.PACKET = saved["use"], saved["pack"], saved["vpacket"]

    def projector_mode(name):
        restore()
        if name == "per-pixel":
            L.use_packets = lambda: False
        elif name == "packets, sums per parameter":
            L.EXPAND_BYTES = 0
        elif name == "packets, PACKET=8":
            L.PACKET = 8

    def voxelizer_mode(name):
        restore()
        if name == "per-voxel":
            V._use_packets = lambda plan: False
            V._pack_chunk = lambda *a: None
        elif name == "packets, gathered values":
            V._pack_chunk = lambda *a: None
        elif name == "packets, PACKET=8":
            V.PACKET = 8

    def clear():
        for v in raw.values():
            dr.clear_grad(v)

    def project_fwd(view):
        with dr.suspend_grad():
            img = P.project_dr(Gaussians.from_raw(raw), geo, angles=geo.angles[view:view + 1],
                               extent=extent)
            dr.eval(img.array)
        dr.sync_thread()

    def project_fb(view):
        img = P.project_dr(Gaussians.from_raw(raw), geo, angles=geo.angles[view:view + 1],
                           extent=extent)
        dr.backward(dr.sum(dr.square(img.array), axis=None))
        dr.eval([dr.grad(v) for v in raw.values()])
        dr.sync_thread()
        clear()

    def voxelize_fwd(start):
        with dr.suspend_grad():
            vol = V.voxelize_dr(Gaussians.from_raw(raw), geo, block=(start, [32] * 3), extent=3.0)
            dr.eval(vol.array)
        dr.sync_thread()

    def voxelize_fb(start):
        vol = V.voxelize_dr(Gaussians.from_raw(raw), geo, block=(start, [32] * 3), extent=3.0)
        dr.backward(tv_3d(vol))
        dr.eval([dr.grad(v) for v in raw.values()])
        dr.sync_thread()
        clear()

    def grads(run, arg):
        """The raw parameters' gradients of one forward + backward (equality check)."""
        if run is project_fb:
            img = P.project_dr(Gaussians.from_raw(raw), geo, angles=geo.angles[arg:arg + 1],
                               extent=extent)
            dr.backward(dr.sum(dr.square(img.array), axis=None))
        else:
            vol = V.voxelize_dr(Gaussians.from_raw(raw), geo, block=(arg, [32] * 3), extent=3.0)
            dr.backward(tv_3d(vol))
        out = [np.asarray(dr.grad(raw[k])).ravel() for k in sorted(raw)]
        clear()
        return out

    views = list(range(0, 25, 2))
    blocks = [[int(x) for x in np.random.default_rng(s).integers(0, 33, 3)] for s in range(10)]
    studies = [
        ("projector (one 96^2 view, extent %.1f)" % extent, projector_mode,
         ["per-pixel", "packets", "packets, sums per parameter", "packets, PACKET=8"],
         [("forward", project_fwd), ("forward + backward", project_fb)], views),
        ("voxelizer + TV (32^3 block, extent 3)", voxelizer_mode,
         ["per-voxel", "packets", "packets, gathered values", "packets, PACKET=8"],
         [("forward", voxelize_fwd), ("forward + backward", voxelize_fb)], blocks),
    ]
    load0 = os.getloadavg()[0]
    results = []
    for title, set_mode, modes, runs, args_ in studies:
        times = {(m, r): [] for m in modes for r, _ in runs}
        cpu = {(m, r): [] for m in modes for r, _ in runs}
        for m in modes:                    # compile every kernel once
            set_mode(m)
            for _, f in runs:
                f(args_[0])
        ref = None
        diff = {}
        for m in modes:                    # same gradients in every configuration
            set_mode(m)
            g = grads(runs[1][1], args_[1])
            if ref is None:
                ref = g
            diff[m] = max(float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
                          for a, b in zip(g, ref))
        for _ in range(args.reps):
            for a in args_:
                for m in modes:
                    set_mode(m)
                    for r, f in runs:
                        t0, c0 = time.perf_counter(), time.process_time()
                        f(a)
                        times[(m, r)].append(1e3 * (time.perf_counter() - t0))
                        cpu[(m, r)].append(1e3 * (time.process_time() - c0))
        restore()
        results.append({"title": title, "modes": modes, "runs": [r for r, _ in runs],
                        "wall_ms": {f"{m} | {r}": statistics.median(v) for (m, r), v in times.items()},
                        "cpu_ms": {f"{m} | {r}": statistics.median(v) for (m, r), v in cpu.items()},
                        "max_gradient_difference_vs_first": diff, "samples": len(args_) * args.reps})
    info = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{os.cpu_count()} CPUs "
            f"({platform.machine()})", "variant": mi_grg.variant(), "packet": saved["packet"],
            "load_before": load0, "load_after": os.getloadavg()[0],
            "code": train_step._git("describe", "--always", "--dirty"), "results": results}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "packets.json").write_text(json.dumps(info, indent=1))
    lines = ["# Packets on and off (`bench/packets.py`)", "",
             f"{info['date']}, {info['machine']}, {info['variant']}, code `{info['code']}`, "
             f"PACKET = {info['packet']}; gr 64^3 state of bench/train_step.py. Medians over "
             "views / blocks (interleaved configurations); load (1 min) "
             f"{load0:.1f} before, {info['load_after']:.1f} after.", ""]
    for res in results:
        first = res["modes"][0]
        lines += [f"## {res['title']}", "",
                  "| configuration | " + " | ".join(f"{r} wall ms | {r} CPU ms" for r in res["runs"])
                  + " | forward + backward vs " + first + " (wall) | gradients vs " + first + " |",
                  "|---|" + "---|" * (2 * len(res["runs"]) + 2)]
        base = res["wall_ms"][f"{first} | {res['runs'][-1]}"]
        for m in res["modes"]:
            cells = []
            for r in res["runs"]:
                cells += [f"{res['wall_ms'][f'{m} | {r}']:.1f}", f"{res['cpu_ms'][f'{m} | {r}']:.1f}"]
            ratio = res["wall_ms"][f"{m} | {res['runs'][-1]}"] / base
            lines.append(f"| {m} | " + " | ".join(cells) + f" | {ratio:.2f}x | "
                         f"{res['max_gradient_difference_vs_first'][m]:.1e} |")
        lines.append("")
    (out / "packets.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
