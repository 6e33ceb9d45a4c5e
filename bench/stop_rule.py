"""The early-stop rule on noisy held-out curves (issue 26): how often it stops a run whose
held-out PSNR is still rising, and how late it stops a real decline, for several
``stop_noise`` values (the margin's multiple of the curve's own scatter; 0 is the rule
before it: 0.5 % of the best alone).

Monte Carlo with ``mi_grg.protocol.early_stop.EarlyStopper`` itself on synthetic held-out
curves shaped like ours: a rise from 20 to 26.5 dB over the unjudged evaluations
(densification), then a straight trend over the judged ones, plus independent Gaussian
scatter of sigma dB per evaluation (our runs: median 0.15 dB, up to 0.53). Two schedules:
64^3 (1500 iterations: 6 unjudged + 3 judged evaluations in the 2/3 window) and 128^3
(3000: 12 + 5; and 12 + 13 with the views held out all run). The rule is also replayed on
every held-out curve logged under ``--results DIR`` (default: the repository's results/, the
experiments' output, when it exists), judged from the run's end of densification.

    .venv/bin/python bench/stop_rule.py [--trials 4000] [--results results]

Writes docs/bench/stop_rule.{json,md}; seconds.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mi_grg.protocol.early_stop import replay as replay_early_stop  # noqa: E402
from mi_grg.training.config import TrainConfig  # noqa: E402
from mi_grg.protocol.early_stop import EarlyStopper  # noqa: E402

NOISES = (0.0, 1.0, 2.0, 3.0)
#: (name, unjudged evaluations, judged evaluations)
SCHEDULES = (("64^3, window 2/3", 6, 3), ("128^3, window 2/3", 12, 5),
             ("128^3, held out all run", 12, 13))
SIGMAS = (0.1, 0.2, 0.4)
SLOPES = (0.0, 0.05, 0.1)        # dB per evaluation after densification (rising or flat)
DECLINE = -0.1                   # dB per evaluation: a real decline


def _judge(values, n_unjudged, noise, drop=0.005, patience=2):
    """Index (among the judged evaluations) where the rule stops, or None."""
    stop, _ = replay_early_stop(range(len(values)), [float(v) for v in values], drop=drop,
                                patience=patience, start=n_unjudged, noise=noise)
    return None if stop is None else stop - n_unjudged


def _curve(rng, n_unjudged, n_judged, slope, sigma):
    rise = 20.0 + 6.5 * (1 - np.exp(-3.0 * np.arange(1, n_unjudged + 1) / n_unjudged)) \
        / (1 - np.exp(-3.0))
    trend = np.concatenate([rise, rise[-1] + slope * np.arange(1, n_judged + 1)])
    return trend + rng.normal(0.0, sigma, trend.size)


def monte_carlo(trials: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    out = {"false_stops": [], "decline": []}
    for name, nu, nj in SCHEDULES:
        for sigma in SIGMAS:
            for slope in SLOPES:
                curves = [_curve(rng, nu, nj, slope, sigma) for _ in range(trials)]
                rates = {str(z): float(np.mean([_judge(c, nu, z) is not None for c in curves]))
                         for z in NOISES}
                out["false_stops"].append({"schedule": name, "sigma": sigma, "slope": slope,
                                           "stop_rate": rates})
        if nj < 8:
            continue        # a decline needs judged evaluations to show in
        for sigma in SIGMAS:
            curves = [_curve(rng, nu, nj, DECLINE, sigma) for _ in range(trials)]
            row = {"schedule": name, "sigma": sigma, "slope": DECLINE, "median_stop": {},
                   "never": {}}
            for z in NOISES:
                at = [_judge(c, nu, z) for c in curves]
                hit = [a for a in at if a is not None]
                row["median_stop"][str(z)] = float(np.median(hit)) if hit else None
                row["never"][str(z)] = float(np.mean([a is None for a in at]))
            out["decline"].append(row)
    return out


def replay(results: Path) -> list:
    """The rule on every logged held-out curve under ``results``."""
    rows = []
    for log in sorted(results.rglob("train_log.csv")):
        with open(log) as f:
            pts = [(int(r["iteration"]), float(r["heldout_psnr"])) for r in csv.DictReader(f)
                   if r.get("heldout_psnr")]
        m = log.parent / "metrics.json"
        if len(pts) < 4 or not m.exists():
            continue
        sched = ((json.loads(m.read_text()).get("method_info") or {}).get("schedule") or {})
        start = sched.get("densify_stop")
        if start is None:
            continue
        row = {"run": str(log.parent.relative_to(results)), "evaluations": len(pts),
               "judged": sum(it >= start for it, _ in pts)}
        its, vals = zip(*pts)
        for z in NOISES:
            row[str(z)] = replay_early_stop(its, vals, drop=0.005, patience=2, start=start,
                                            noise=z)[0]
        s = EarlyStopper()
        for it, v in pts:
            s.observe(it, v)
        row["scatter"] = s.scatter()
        rows.append(row)
    return rows


def markdown(res: dict) -> str:
    z = [str(x) for x in NOISES]
    md = ["# Early-stop rule on noisy held-out curves (`bench/stop_rule.py`)", "",
          f"{res['trials']} synthetic curves per cell (seed 0), `EarlyStopper(drop=0.005, "
          "patience=2, noise=z)`; sigma: the held-out PSNR's scatter per evaluation (dB), "
          "slope: its trend per judged evaluation (dB). TrainConfig's default: "
          f"`stop_noise = {TrainConfig().protocol.stop_noise:g}`.", "",
          "## Runs stopped while the held-out PSNR is level or rising", "",
          "| schedule (unjudged + judged evaluations) | sigma | slope | "
          + " | ".join(f"z = {x}" for x in z) + " |",
          "|---|---|---|" + "---|" * len(z)]
    for r in res["false_stops"]:
        md.append(f"| {r['schedule']} | {r['sigma']} | {r['slope']} | "
                  + " | ".join(f"{r['stop_rate'][x]:.3f}" for x in z) + " |")
    md += ["", f"## A real decline ({DECLINE} dB per judged evaluation): judged evaluations "
           "until the stop (median; share never stopped)", "",
           "| schedule | sigma | " + " | ".join(f"z = {x}" for x in z) + " |",
           "|---|---|" + "---|" * len(z)]
    for r in res["decline"]:
        cells = [("-" if r["median_stop"][x] is None else f"{r['median_stop'][x]:.0f}")
                 + f" ({r['never'][x]:.2f})" for x in z]
        md.append(f"| {r['schedule']} | {r['sigma']} | " + " | ".join(cells) + " |")
    if res.get("replay"):
        rep = res["replay"]
        md += ["", f"## Replayed on {len(rep)} logged runs ({res['results']})", "",
               "Runs the rule would stop (iteration), by z; all others ran to their window's "
               "end or budget.", "",
               "| run | judged evaluations | scatter (dB) | " + " | ".join(f"z = {x}" for x in z)
               + " |", "|---|---|---|" + "---|" * len(z)]
        for r in rep:
            if any(r[x] is not None for x in z):
                md.append(f"| {r['run']} | {r['judged']} | {r['scatter']:.3f} | "
                          + " | ".join("-" if r[x] is None else str(r[x]) for x in z) + " |")
        sc = sorted(r["scatter"] for r in rep)
        md += ["", f"Scatter over the {len(sc)} runs: median {np.median(sc):.3f} dB, "
               f"90th percentile {np.percentile(sc, 90):.3f}, max {sc[-1]:.3f}."]
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=4000)
    ap.add_argument("--results", default=str(ROOT / "results"),
                    help="replay the rule on every train_log.csv under this folder "
                         "(skipped when it does not exist)")
    ap.add_argument("--json", default=str(ROOT / "docs/bench/stop_rule.json"))
    ap.add_argument("--md", default=str(ROOT / "docs/bench/stop_rule.md"))
    args = ap.parse_args(argv)
    if args.trials < 10:
        ap.error(f"--trials must be >= 10, got {args.trials}")
    res = {"trials": args.trials, **monte_carlo(args.trials)}
    if args.results and Path(args.results).is_dir():
        res["results"] = os.path.relpath(args.results, ROOT)
        res["replay"] = replay(Path(args.results))
    Path(args.json).write_text(json.dumps(res, indent=1))
    Path(args.md).write_text(markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
