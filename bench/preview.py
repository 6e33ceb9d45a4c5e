"""The 3-D preview's time: ``mi-grg render --run RUN --preview`` end to end, in a fresh
process each time (Mitsuba import, kernel compilation, rendering, PNG and GIF included).

Usage:  .venv/bin/python bench/preview.py --run out/demo/gr [--repeats 3]
            [--out docs/bench/preview.md]

Without ``--run`` it simulates the demo's 64^3 Shepp-Logan scan and reconstructs it with
FDK (the preview's cost depends on the grid size, not on the method). Target (issue
"Results where CT people look at them"): under 60 s at 64^3 on the 2-core CPU.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_S = 60.0
ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "mi_grg.cli"]


def _fdk_run(tmp: Path) -> Path:
    subprocess.run(CLI + ["simulate", "--phantom", "shepp", "--n", "64", "--out",
                          str(tmp / "shepp")], check=True, capture_output=True)
    subprocess.run(CLI + ["reconstruct", str(tmp / "shepp"), "--method", "fdk", "--out",
                          str(tmp / "fdk")], check=True, capture_output=True)
    return tmp / "fdk"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", help="a finished run (default: FDK of the demo's scan)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "preview.md"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(args.run) if args.run else _fdk_run(Path(tmp))
        times, loads = [], []
        for k in range(args.repeats):
            loads.append(os.getloadavg()[0])
            t0 = time.perf_counter()
            subprocess.run(CLI + ["render", "--run", str(run), "--preview", "--out",
                                  str(Path(tmp) / f"preview{k}")], check=True,
                           capture_output=True)
            times.append(time.perf_counter() - t0)
        import numpy as np
        shape = "x".join(map(str, np.load(run / "vol_pred.npy", mmap_mode="r").shape))
    med = statistics.median(times)
    lines = [
        "# 3-D preview time (`bench/preview.py`)", "",
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average at the starts {', '.join(f'{x:.1f}' for x in loads)}.", "",
        f"`mi-grg render --run {run} --preview` ({shape} voxels, 24 azimuths of 256^2, "
        f"4 spp), a fresh process each: {', '.join(f'{t:.1f}' for t in times)} s, median "
        f"{med:.1f} s (target < {TARGET_S:g} s: {'met' if med < TARGET_S else 'missed'}).", ""]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
