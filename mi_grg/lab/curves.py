"""Methods that experiments add to ``mi_grg.methods``: SART / ASD-POCS wrappers that log
3-D PSNR after every sweep (the speed curves), and a suite's ``extra_methods``."""
from __future__ import annotations

import time
from pathlib import Path

from mi_grg.lab.suite import CURVE_METHODS


def register_experiment_methods(extra: dict | None = None) -> None:
    """Register the curve-logging wrappers (sart-curve, asd-pocs-curve) and a suite's
    ``extra_methods`` ({name: "module:function"}) with ``mi_grg.methods``."""
    import importlib
    from mi_grg.methods import METHODS, register_method
    for base, name in CURVE_METHODS.items():
        if name not in METHODS:
            register_method(name, _curve_method(base))
    for name, target in (extra or {}).items():
        module, func = target.split(":")
        register_method(name, getattr(importlib.import_module(module), func))



def _curve_method(kind: str):
    """``kind`` ("sart" / "asd-pocs" / "pdhg", a fixed setting) with a per-sweep log of
    (seconds, 3-D PSNR) written to OUT/progress_log.csv; the time spent scoring is excluded
    from the logged seconds."""
    def run(case, out_dir=None, progress: bool = True, **options):
        from mi_grg.classical import iterative, pdhg
        from mi_grg.evaluation.metrics import psnr_3d
        rows, spent = [], [0.0]
        t0 = time.perf_counter()

        def callback(it, vol):
            t = time.perf_counter()
            row = {"iteration": it + 1, "seconds": round(t - t0 - spent[0], 4)}
            if case.vol_gt is not None:
                row["psnr_3d"] = float(psnr_3d(vol, case.vol_gt))
            rows.append(row)
            spent[0] += time.perf_counter() - t

        func = {"sart": iterative.sart, "asd-pocs": iterative.asd_pocs, "pdhg": pdhg.pdhg}[kind]
        vol = func(case.train, case.geometry, callback=callback, progress=progress, **options)
        if out_dir is not None:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            with open(Path(out_dir) / "progress_log.csv", "w") as f:
                f.write("iteration,seconds,psnr_3d\n")
                for r in rows:
                    f.write(f"{r['iteration']},{r['seconds']},{r.get('psnr_3d', '')}\n")
        return vol, {"curve": rows, "scoring_seconds_excluded": spent[0], "base_method": kind}
    run.__name__ = f"reconstruct_{kind.replace('-', '_')}_curve"
    return run
