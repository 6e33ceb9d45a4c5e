"""The field's result (mi_grg.training.result): one gr training per case, then each step of
its result on the same trained state, beside the refinement it replaced and the classical
step alone.

For each case: gr's default training; the Gaussians alone (centre samples), voxel-averaged,
the anchored refinement's grid, the exported Gaussians (= vol_pred); the replaced default
(Morozov's weight, held-out length, a voxel grid) when ``--old-refine`` names its module
(``git show d7f240b:mi_grg/training/refine.py > /tmp/old_refine.py``); cold PDHG at the
refinement's weight from zero, its 3-D PSNR at 60 ... 1000 iterations (converged by 750);
PDHG as ``--method pdhg`` runs it under each of its weight rules (``PDHG_RULES``).
Tuning cases chose the defaults (voxel_average 0.75, refine_lam 0.003); confirmation cases
(other seeds, shared/data volumes) were run once with them.

    MI_GRG_DATA=/work/shared/data python experiments/studies/field_result.py \\
        --cases needles needles7 --data /tmp/field_data --old-refine /tmp/old_refine.py
    MI_GRG_DATA=/work/shared/data python experiments/studies/field_result.py \\
        --cases needles7 --n 128 --data /tmp/field_data          # 128^3, detector 192^2

Writes docs/bench/field_result.json (one record per case, merged with earlier ones) and
docs/bench/field_result.md.
"""
import argparse
import importlib.util
import json
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("MI_GRG_DATA", ROOT.parent / "shared" / "data"))
#: name: (source, seed, set)
CASES = {
    "needles": ("needles", 0, "tuning"), "shepp": ("shepp", 0, "tuning"),
    "shells": ("shells", 0, "tuning"), "bone": ("bone_128.npy", 0, "tuning"),
    "needles7": ("needles", 7, "confirmation"), "shells7": ("shells", 7, "confirmation"),
    "cement": ("cement_128.npy", 0, "confirmation"),
    "mni152": ("mni152_128.npy", 0, "confirmation"),
}
COLD_AT = (60, 100, 200, 300, 500, 750, 1000)


#: PDHG's own weight rules (``lam_rule``), each under its held-out protocol from zero.
PDHG_RULES = ("one_se", "best", "morozov")


def pdhg_run(case, **options) -> dict:
    """``--method pdhg`` with ``options``: its 3-D PSNR, time and the held-out choice."""
    import mi_grg
    t0 = time.perf_counter()
    _, m = mi_grg.reconstruct(case, "pdhg", progress=False, **options)
    chosen = m.get("method_info", {}).get("chosen", {})
    return {"psnr": m["psnr_3d"], "seconds": time.perf_counter() - t0,
            "lam": chosen.get("setting", {}).get("lam"), "iterations": chosen.get("sweeps")}


def pdhg_rules(case) -> dict:
    """PDHG as ``--method pdhg`` runs it, under each of its weight rules."""
    return {rule: pdhg_run(case, lam_rule=rule) for rule in PDHG_RULES}


def save_record(out: Path, key: str, rec: dict, markdown) -> None:
    """Merge ``rec`` under ``key`` into ``out``.json (re-read first: two processes may
    write cases of their own) and rewrite ``out``.md as ``markdown(records)``."""
    path = out.with_suffix(".json")
    records = json.loads(path.read_text()) if path.exists() else {}
    records[key] = rec
    path.write_text(json.dumps(records, indent=1))
    out.with_suffix(".md").write_text(markdown(records))


def make_case(name: str, n: int, data_root: Path, cases=None) -> tuple:
    """(the case ``name`` of ``cases`` (None: ``CASES``) at n^3, detector 1.5 n, 25 noisy
    views; its set)."""
    from mi_grg.lab.runner import suite_case
    from mi_grg.lab.suite import CaseSpec
    src, seed, which = (CASES if cases is None else cases)[name]
    src = str(DATA / src) if src.endswith(".npy") else src
    spec = CaseSpec(name=name, category="-", source=src, views=25, test_views=25, n=n,
                    det=int(1.5 * n), noise={"I0": 1e4, "electronic_std": 10.0}, seed=seed,
                    data_name=f"{name}_{n}")
    return suite_case(spec, data_root), which


def run_case(name: str, data_root: Path, old_refine, n: int = 64) -> dict:
    from mi_grg.classical.pdhg import PDHG
    from mi_grg.evaluation.metrics import psnr_3d
    from mi_grg.training import result
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    case, which = make_case(name, n, data_root)

    def ps(v):
        return float(psnr_3d(v, case.vol_gt))
    rec = {"case": name, "set": which, "n": n}
    t0 = time.perf_counter()
    cfg = make_config("gr")
    tr = Trainer(case, cfg, progress=False)
    rec["n_gaussians"] = tr.run()["n_gaussians"]
    rec["train_seconds"] = time.perf_counter() - t0
    if old_refine is not None:
        t0 = time.perf_counter()
        vol, info = old_refine.refine_tv(tr, progress=False)
        rec["old_default"] = {"psnr": ps(vol), "lam": info.get("lam"),
                              "iterations": info.get("iterations"),
                              "seconds": time.perf_counter() - t0}
    t0 = time.perf_counter()
    vol, g, info = result.finish(tr, progress=False)
    rec["new"] = {"psnr": ps(vol), "parts": info["parts"],
                  "seconds": time.perf_counter() - t0,
                  "refine": {k: v for k, v in info.get("refine", {}).items() if k != "curve"},
                  "export_psnr": ps(result.field_volume(tr, g))}
    geo = case.geometry
    t0 = time.perf_counter()
    s = PDHG(case.train, geo, geo.angles, lam=cfg.protocol.refine_lam)
    curve = []
    for it in range(1, COLD_AT[-1] + 1):
        s.step()
        if it in COLD_AT:
            curve.append((it, ps(np.asarray(s.x.numpy(), np.float32).reshape(geo.nVoxel))))
    rec["cold_pdhg"] = {"lam": cfg.protocol.refine_lam, "curve": curve,
                        "seconds": time.perf_counter() - t0}
    rec["pdhg_rules"] = pdhg_rules(case)
    return rec


def markdown(records: dict) -> str:
    head = ("| case | n | set | Gaussians alone | voxel-averaged | refined grid | **gr (export "
            "= vol_pred)** | replaced default | cold PDHG lam 0.003, 60 / 300 / 1000 it. (best)"
            " | PDHG one-SE / best / Morozov | refine iterations (cap) | train + result s |"
            "\n|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = [head]
    for which in ("tuning", "confirmation"):
        for r in (r for r in records.values() if r["set"] == which):
            p, n = r["new"]["parts"], r["new"]
            cold = dict(r["cold_pdhg"]["curve"])
            old = r.get("old_default", {}).get("psnr")
            ref = n["refine"]
            rules = r.get("pdhg_rules")
            rules = " / ".join(f"{rules[k]['psnr']:.2f}" for k in PDHG_RULES) if rules else "-"
            rows.append(
                f"| {r['case']} | {r.get('n', 64)} | {which} | {p['gaussians']:.2f} | "
                f"{p['voxel_averaged']:.2f} | {p['refined_grid']:.2f} | **{n['psnr']:.2f}** | "
                f"{'-' if old is None else f'{old:.2f}'} | {cold[60]:.2f} / {cold[300]:.2f} / "
                f"{cold[1000]:.2f} ({max(cold.values()):.2f}) | {rules} | "
                f"{ref.get('iterations')} ({ref.get('cap')}) | "
                f"{r['train_seconds']:.0f} + {n['seconds']:.0f} |")
    for which in ("tuning", "confirmation"):
        rs = [r for r in records.values() if r["set"] == which and "old_default" in r]
        if rs:
            gain = np.mean([r["new"]["psnr"] - r["old_default"]["psnr"] for r in rs])
            rows.append(f"\nMean gain over the replaced default, {which} ({len(rs)} cases): "
                        f"{gain:+.2f} dB.")
    return "\n".join(rows) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--n", type=int, default=64, help="volume size (detector 1.5 n)")
    ap.add_argument("--data", type=Path, default=Path("/tmp/field_result_data"))
    ap.add_argument("--old-refine", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "field_result")
    a = ap.parse_args()
    old = None
    if a.old_refine is not None:
        spec = importlib.util.spec_from_file_location("old_refine", a.old_refine)
        old = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(old)
    path = a.out.with_suffix(".json")
    records = json.loads(path.read_text()) if path.exists() else {}
    for name in a.cases:
        key = name if a.n == 64 else f"{name}_{a.n}"
        records[key] = run_case(name, a.data, old, a.n)
        path.write_text(json.dumps(records, indent=1))
        a.out.with_suffix(".md").write_text(markdown(records))
        print(json.dumps(records[key]))


if __name__ == "__main__":
    main()
