"""The paper's experiments as run plans: ``plan_experiment`` turns an experiment of a suite
into ``RunSpec``s (one reconstruction each); Table 2's rows live in ``table2_variants``."""
from __future__ import annotations

import dataclasses
import inspect
import json
from dataclasses import dataclass
from pathlib import Path

from mi_grg.lab.curves import register_experiment_methods
from mi_grg.lab.suite import (ALL_METHODS, COLD_FACTOR, COLD_ROW, CURVE_METHODS, EXPERIMENTS,
                              FIXED_ROWS, RULE_ROWS, NOSTOP_DROP, TRAINED, CaseSpec, Suite)


@dataclass
class RunSpec:
    """One reconstruction: ``OUT/<experiment>/<case>/<run>/`` on data ``OUT/data/<data>``."""
    experiment: str
    case: CaseSpec
    run: str
    method: str
    options: dict
    label: str = ""             # what the run stands for in tables (e.g. "views=10")

    def run_dir(self, out: Path) -> Path:
        return Path(out) / self.experiment / self.case.name / self.run

    def data_dir(self, out: Path) -> Path:
        return Path(out) / "data" / self.case.data_dir_name

    def key(self) -> str:
        """Identity of the computation (data, method, options): equal keys, equal results."""
        return json.dumps({"case": self.case.key(), "method": self.method,
                           "options": self.options}, sort_keys=True, default=str)

    def to_dict(self) -> dict:
        return {"experiment": self.experiment, "case": dataclasses.asdict(self.case),
                "run": self.run, "method": self.method, "options": self.options,
                "label": self.label}



def _train_fields() -> set:
    from mi_grg.training.config import FLAT_KEYS
    return set(FLAT_KEYS)


def canonical_options(method: str, options: dict) -> dict:
    """``options`` without entries equal to the method's defaults (so that e.g. gr with
    k=6 and gr with no options are recognised as the same run)."""
    from mi_grg.methods import get_method
    options = dict(options)
    if method in TRAINED:
        from mi_grg.training.config import make_config
        base = make_config(method).to_flat()
        cfg = make_config(method, **{k: v for k, v in options.items() if k in base})
        return {k: v for k, v in options.items()
                if k not in base or cfg.to_flat()[k] != base[k]}
    try:
        params = inspect.signature(get_method(method)).parameters
    except (ValueError, TypeError):
        return options
    return {k: v for k, v in options.items()
            if not (k in params and params[k].default is not inspect.Parameter.empty
                    and params[k].default == v)}


def _cold_options(suite: Suite) -> dict:
    """PDHG from zero at gr's refinement weight, ``COLD_FACTOR`` x its iteration cap (the
    suite's gr options or TrainConfig's defaults)."""
    from mi_grg.training.config import make_config
    gr = suite.method_options.get("gr", {})
    proto = make_config("gr").protocol
    lam = float(gr.get("refine_lam", proto.refine_lam))
    cap = int(gr.get("refine_max_iterations", proto.refine_max_iterations))
    return _opts(suite, "pdhg", stop="none", lam=lam, n_iter=COLD_FACTOR * cap)


def _opts(suite: Suite, method: str, **extra) -> dict:
    base = CURVE_METHODS_INV.get(method, method)
    return canonical_options(method, {**suite.method_options.get(base, {}), **extra})


CURVE_METHODS_INV = {v: k for k, v in CURVE_METHODS.items()}


def _log3d_options(ecfg: dict) -> dict:
    """Options that log 3-D PSNR during training without letting it stop the run: the
    ``log_3d_every`` TrainConfig option when it exists, else nothing."""
    every = int(ecfg.get("log_3d_every", 0) or 0)
    if every and "log_3d_every" in _train_fields():
        return {"log_3d_every": every}
    return {}


def table2_variants() -> list:
    """Table 2's rows in order: (run, method, options, label); each ablation row is r2 plus
    one component at gr's default."""
    from mi_grg.training.config import TrainConfig
    d = TrainConfig()
    return [("r2", "r2", {}, "R2-Gaussian (baseline)"),
            ("r2+deinit", "r2", {"sigma_d": d.deinit.sigma_d}, "+ De-Init"),
            ("r2+pga", "r2", {"use_pga": True}, "+ PGA"),
            # the Laplacian alone: with r2+graph it separates the field's effect
            ("r2+lap", "r2", {"lambda_lap": d.graph.lambda_lap}, "+ Laplacian"),
            ("r2+graph", "r2", {"use_graph_field": True, "lambda_lap": d.graph.lambda_lap},
             "+ graph field & Laplacian"),
            # beyond the paper: gr's default voxel-averages and refines its field
            # (mi_grg.training.result)
            ("r2+refine", "r2", {"refine": d.protocol.refine,
                                 "voxel_average": d.protocol.voxel_average},
             "+ voxel average & TV refinement"),
            ("gr", "gr", {}, "GR-Gaussian (all)")]


def plan_experiment(name: str, suite: Suite, methods=None, cases=None) -> list:
    """The runs of experiment ``name`` on ``suite`` (optionally restricted to ``methods``
    (base method names, or row names such as "gr-paper" or "pdhg-cold") and ``cases`` (case
    names))."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; choose one of {list(EXPERIMENTS)} "
                         f"or 'all'")
    register_experiment_methods(suite.extra_methods)
    ecfg = suite.experiments.get(name) or {}
    names = list(cases) if cases else (ecfg.get("cases") or [c.name for c in suite.cases])
    case_list = [suite.case(n) for n in names]
    want = set(methods) if methods else None
    specs = []

    def add(case, run, method, options, label=""):
        base = CURVE_METHODS_INV.get(method, method)
        if want is None or base in want or method in want or run in want:
            specs.append(RunSpec(name, case, run, method, options, label or run))

    for case in case_list:
        if name == "table1":
            for m in ecfg.get("methods") or ALL_METHODS:
                add(case, m, m, _opts(suite, m))
                if m == "gr":   # the paper's configuration (scenes/gr_paper.xml) keeps a row
                    add(case, "gr-paper", m, _opts(suite, m, refine="none", voxel_average=0.0),
                        "gr (the paper's configuration)")
                if m in FIXED_ROWS:
                    add(case, f"{m}-fixed", m, _opts(suite, m, **FIXED_ROWS[m]),
                        f"{m} (fixed {FIXED_ROWS[m]['n_iter']} sweeps)")
                for run, options, label in RULE_ROWS.get(m, ()):
                    add(case, run, m, _opts(suite, m, **options), label)
                if m == "gr":
                    add(case, COLD_ROW[0], "pdhg", _cold_options(suite), COLD_ROW[1])
        elif name == "table2":
            for run, m, o, label in table2_variants():
                add(case, run, m, _opts(suite, m, **o), label)
        elif name == "table3":
            for k in ecfg.get("k") or [4, 5, 6, 7, 8]:
                add(case, f"k{k}", "gr", _opts(suite, "gr", k=int(k)), f"k={k}")
            for s in ecfg.get("sigma_d") or [1, 2, 3, 4, 5]:
                add(case, f"sigma_d{s:g}", "gr", _opts(suite, "gr", sigma_d=float(s)),
                    f"sigma_d={s:g}")
        elif name == "iterations":
            log3d = _log3d_options(ecfg)
            for m in ecfg.get("methods") or ["gr"]:
                add(case, m, m, _opts(suite, m, **log3d), f"{m} (early stop)")
                # The full schedule, never stopped, shows the decline after the peak. With no
                # log_3d_every option, monitor_3d logs 3-D PSNR; with stop_drop 0.99 it
                # cannot stop the run (it only picks the returned state: research only).
                extra = log3d or ({"monitor_3d": True} if ecfg.get("log_3d_every") else {})
                add(case, f"{m}-nostop", m, _opts(suite, m, stop_drop=NOSTOP_DROP, **extra),
                    f"{m} (no early stop)")
        elif name == "speed":
            log3d = _log3d_options(suite.experiments.get("iterations") or ecfg)
            for m in ecfg.get("methods") or ALL_METHODS:
                if m in CURVE_METHODS:
                    add(case, m, CURVE_METHODS[m], _opts(suite, CURVE_METHODS[m]), m)
                elif m in TRAINED:
                    add(case, m, m, _opts(suite, m, **log3d), m)
                else:
                    add(case, m, m, _opts(suite, m), m)
        elif name == "views":
            for v in ecfg.get("views") or [10, 25, 50, 75]:
                v = int(v)
                vc = case if v == case.views else dataclasses.replace(
                    case, views=v, data_name=f"{case.name}_v{v}")
                for m in ecfg.get("methods") or ALL_METHODS:
                    add(vc, f"{m}_v{v}", m, _opts(suite, m), f"{m}, {v} views")
        elif name == "seeds":
            # The training seed draws the De-Init sample, the view order, the TV blocks and
            # the split positions; the data (and its noise) stay fixed. Seed 0 is Table 1's
            # run (same options), linked rather than run again.
            for sd in ecfg.get("seeds") or [0, 1, 2]:
                for m in ecfg.get("methods") or TRAINED:
                    add(case, f"{m}_s{int(sd)}", m, _opts(suite, m, seed=int(sd)),
                        f"{m}, seed {int(sd)}")
    return specs


def check_method_filter(names: list, suite: Suite, methods, specs: list) -> None:
    """A ``--methods`` name that no run of experiments ``names`` uses (as its method or its
    row) is an error naming the methods and rows they do have (a misspelt name would
    otherwise plan nothing, silently)."""
    def used(runs):
        return {n for r in runs for n in (r.method, CURVE_METHODS_INV.get(r.method, r.method))}
    every = [s for n in names for s in plan_experiment(n, suite)]
    unknown = [m for m in methods or () if m not in used(specs) | {r.run for r in specs}]
    if unknown:
        rows = sorted({r.run for r in every} - used(every))
        raise ValueError(f"--methods {','.join(unknown)}: no run of {', '.join(names)} uses "
                         f"it; their methods: {', '.join(sorted(used(every)))}; their rows: "
                         f"{', '.join(rows)}")
