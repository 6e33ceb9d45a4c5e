"""What a trained field's Gaussian count costs per training step: the projection of one
view, forward and backward, for trained states of one case, alternated so that every state
sees the same machine load.

    .venv/bin/python bench/count_speed.py results/cpu128/data/shepp \
        default=RUN_A/checkpoint.npz cap65k=RUN_B/checkpoint.npz [--reps 6]

Each state is a run's checkpoint (its current parameters); every repeat projects one
random training view of the case with each state in turn and back-propagates the mean
absolute image (the first repeat warms the kernels and is not timed). Medians per state and
their ratio to the first are written to docs/bench/count_speed.json and .md.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "bench" / "count_speed"


def measure(data: str, states: dict, reps: int, seed: int = 0) -> dict:
    import numpy as np
    import mi_grg  # noqa: F401  (first: it points Dr.Jit at a suitable LLVM, selects the variant)
    import drjit as dr
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.projector import project_dr
    from mi_grg.data.dataset import load_case
    from mi_grg.training.checkpoint import raw_parameters
    from mi_grg.training.config import TRAIN_EXTENT
    geo = load_case(data).geometry
    raws = {label: raw_parameters(path) for label, path in states.items()}
    rng = np.random.default_rng(seed)
    times = {label: [] for label in raws}
    for rep in range(reps + 1):
        for label, raw in raws.items():
            for v in raw.values():
                dr.enable_grad(v)
            angle = geo.angles[rng.integers(geo.n_views)]
            t0 = time.perf_counter()
            img = project_dr(Gaussians.from_raw(raw), geo, np.array([angle]), extent=TRAIN_EXTENT)
            dr.backward(dr.mean(dr.abs(img.array)))
            dr.eval(*[dr.grad(v) for v in raw.values()])
            dr.sync_thread()
            if rep:
                times[label].append(time.perf_counter() - t0)
            for v in raw.values():
                dr.clear_grad(v)
    first = next(iter(times))
    base = statistics.median(times[first])
    return {"data": data, "reps": reps, "load": os.getloadavg()[0],
            "states": {label: {"checkpoint": str(states[label]),
                               "n_gaussians": int(dr.width(raws[label]["raw_densities"])),
                               "median_s": statistics.median(t),
                               "ratio": statistics.median(t) / base}
                       for label, t in times.items()}}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="the case folder the states were trained on")
    ap.add_argument("states", nargs="+", help="LABEL=CHECKPOINT (the first is the reference)")
    ap.add_argument("--reps", type=int, default=6)
    a = ap.parse_args(argv)
    states = dict(s.split("=", 1) for s in a.states)
    rec = measure(a.data, states, a.reps)
    OUT.with_suffix(".json").write_text(json.dumps(rec, indent=1) + "\n")
    lines = ["# Projection cost by Gaussian count (`bench/count_speed.py`)", "",
             f"Case {rec['data']}; one view forward + backward, median of {rec['reps']} "
             f"alternated repeats; 1-minute load {rec['load']:.2f} at the end.", "",
             "| state | Gaussians | seconds | ratio |", "|---|---|---|---|"]
    for label, s in rec["states"].items():
        lines.append(f"| {label} | {s['n_gaussians']} | {s['median_s']:.3f} | "
                     f"{s['ratio']:.2f} |")
    OUT.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
