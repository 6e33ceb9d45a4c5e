"""Scripted experiments: a suite of cases (JSON), the paper's experiments as run plans, and a
resumable, parallel runner.

    mi-grg experiment NAME --suite experiments/suite_cpu.json --out results/cpu [--jobs N]
                           [--methods a,b] [--cases x,y] [--dry-run]
    mi-grg report --out results/cpu [--report docs/results.md]

NAME is one of ``EXPERIMENTS`` or "all" (the experiments the suite's ``experiments`` block
lists, or every one when it lists none):
    table1      every method x every case (3-D PSNR / SSIM, time)
    table2      ablation: r2, r2 + De-Init, r2 + PGA, r2 + Laplacian, r2 + graph field &
                Laplacian, gr
    table3      sweeps of k (kNN graph) and sigma_d (De-Init filter)
    iterations  held-out-view PSNR and 3-D PSNR against iteration, early stop marked
    speed       3-D PSNR against wall-clock time for every method
    views       10 / 25 / 50 / 75 training views
    seeds       r2 and gr with several training seeds (default 0, 1, 2): the run-to-run
                spread that a difference between the two must exceed to count

Layout: ``OUT/data/<case>/`` (simulated once, R2-Gaussian layout, reused),
``OUT/<experiment>/<case>/<run>/`` (the reconstruction contract's files plus run_spec.json,
log.txt, and error.txt on failure), ``OUT/<experiment>/runs.json`` (status of every run),
``OUT/suite.json`` (the suite last run). A run whose metrics.json exists is not rerun,
unless it is an r2/gr run whose recorded training config differs from what this code
resolves its options to (a default changed since: ``stale_options``); a run identical to
one done elsewhere in OUT (same data, method and options) becomes a relative symlink to it
instead of running again. ``OUT/<experiment>/runs.json`` is rewritten as runs finish.

Runs execute in spawned worker processes (Dr.Jit is not fork-safe), one fresh process per
run, ``jobs`` at a time, each with ``cores // jobs`` Dr.Jit threads. A failing run writes
error.txt and does not stop the others.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import inspect
import json
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

EXPERIMENTS = ("table1", "table2", "table3", "iterations", "speed", "views", "seeds")
#: Keys each experiment's block in a suite may set (anything else is an error).
EXPERIMENT_KEYS = {"table1": ("methods", "cases"), "table2": ("cases",),
                   "table3": ("k", "sigma_d", "cases"),
                   "iterations": ("methods", "log_3d_every", "cases"),
                   "speed": ("methods", "cases"), "views": ("views", "methods", "cases"),
                   "seeds": ("seeds", "methods", "cases")}
ALL_METHODS = ("fdk", "sart", "asd-pocs", "pdhg", "r2", "gr")
CATEGORIES = {"HO": "human organs / organ-like", "BS": "biological specimens",
              "AO": "artificial objects"}
CASE_FIELDS = ("name", "category", "source", "views", "test_views", "n", "det", "mode",
               "noise", "seed")
TRAINED = ("r2", "gr")               # methods configured by mi_grg.training.config.TrainConfig
CURVE_METHODS = {"sart": "sart-curve", "asd-pocs": "asd-pocs-curve", "pdhg": "pdhg-curve"}
#: Table 1's second row for the iterative classical methods: the paper's fixed sweep count
#: (their default stops on held-out views, mi_grg.classical.heldout).
FIXED_ROWS = {"sart": {"n_iter": 10, "stop": "none"},
              "asd-pocs": {"n_iter": 10, "stop": "none"}}
NOSTOP_DROP = 0.99                   # stop_drop that never triggers (iteration analysis)


class SuiteError(ValueError):
    """An invalid suite file; the message names the field."""


# ---------------------------------------------------------------------------- suite
@dataclass(frozen=True)
class CaseSpec:
    """One simulated scan (all sizes in voxels / pixels; noise as NoiseModel fields)."""
    name: str
    category: str
    source: str                 # phantom name (mi_grg.data.phantoms) or a .npy volume
    views: int
    test_views: int
    n: int
    det: int
    mode: str = "cone"
    noise: dict | None = None
    seed: int = 0
    oversample: float = 4.0     # volume sources: samples per source voxel (volume_phantom)
    ground_truth: str = "average"   # volume sources: "average" | "block"
    data_name: str = ""         # directory under OUT/data ("" -> name)

    @property
    def data_dir_name(self) -> str:
        return self.data_name or self.name

    @property
    def is_volume(self) -> bool:
        return self.source.endswith(".npy")

    def key(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("data_name")
        d.pop("category")
        if not self.is_volume:
            d.pop("oversample")
            d.pop("ground_truth")
        return d


@dataclass
class Suite:
    name: str
    path: str
    variant: str
    cases: list
    method_options: dict = field(default_factory=dict)
    experiments: dict = field(default_factory=dict)
    extra_methods: dict = field(default_factory=dict)
    description: str = ""

    def case(self, name: str) -> CaseSpec:
        for c in self.cases:
            if c.name == name:
                return c
        raise SuiteError(f"suite {self.path} has no case {name!r}; cases: "
                         f"{[c.name for c in self.cases]}")


def _int_field(c: dict, key: str, where: str, minimum: int) -> int:
    v = c[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise SuiteError(f"{where}.{key} must be an integer >= {minimum}, got {v!r}")
    return v


def load_suite(path) -> Suite:
    """Read and validate a suite JSON file (see experiments/README.md for the format)."""
    from mi_grg.data.phantoms import PHANTOMS
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SuiteError(f"cannot read suite {path}: {e}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("cases"), list) or not raw["cases"]:
        raise SuiteError(f"{path}: expected an object with a non-empty 'cases' list")
    cases, seen = [], set()
    known = {f.name for f in dataclasses.fields(CaseSpec)} - {"data_name"}
    for i, c in enumerate(raw["cases"]):
        where = f"{path}: cases[{i}]"
        if not isinstance(c, dict):
            raise SuiteError(f"{where} must be an object")
        missing = [k for k in CASE_FIELDS if k not in c]
        if missing:
            raise SuiteError(f"{where} lacks {missing}")
        unknown = sorted(set(c) - known)
        if unknown:
            raise SuiteError(f"{where} has unknown field(s) {unknown}; known: {sorted(known)}")
        name = c["name"]
        if not isinstance(name, str) or not name or any(ch in name for ch in "/\\ ") \
                or name == "data":
            raise SuiteError(f"{where}.name must be a non-empty name without / \\ or spaces "
                             f"(and not 'data'), got {name!r}")
        if name in seen:
            raise SuiteError(f"{where}: duplicate case name {name!r}")
        seen.add(name)
        if c["category"] not in CATEGORIES:
            raise SuiteError(f"{where}.category must be one of {list(CATEGORIES)}, got "
                             f"{c['category']!r}")
        src = c["source"]
        if not isinstance(src, str) or not (src in PHANTOMS or src.endswith(".npy")):
            raise SuiteError(f"{where}.source must be a phantom {PHANTOMS} or a .npy volume, "
                             f"got {src!r}")
        if c["mode"] not in ("cone", "parallel"):
            raise SuiteError(f"{where}.mode must be 'cone' or 'parallel', got {c['mode']!r}")
        noise = c["noise"]
        if noise is not None:
            if not isinstance(noise, dict):
                raise SuiteError(f"{where}.noise must be null or {{I0, electronic_std}}")
            from mi_grg.data.noise import NoiseModel
            try:
                NoiseModel(**noise)
            except (TypeError, ValueError) as e:
                raise SuiteError(f"{where}.noise: {e}") from None
        spec = CaseSpec(name=name, category=c["category"], source=src,
                        views=_int_field(c, "views", where, 2),
                        test_views=_int_field(c, "test_views", where, 0),
                        n=_int_field(c, "n", where, 2), det=_int_field(c, "det", where, 2),
                        mode=c["mode"], noise=noise, seed=_int_field(c, "seed", where, 0),
                        oversample=float(c.get("oversample", 4.0)),
                        ground_truth=c.get("ground_truth", "average"))
        cases.append(spec)
    mo = raw.get("method_options", {}) or {}
    if not isinstance(mo, dict) or not all(isinstance(v, dict) for v in mo.values()):
        raise SuiteError(f"{path}: method_options must map method names to option objects")
    ex = raw.get("experiments", {}) or {}
    bad = sorted(set(ex) - set(EXPERIMENTS))
    if bad:
        raise SuiteError(f"{path}: unknown experiment(s) {bad}; known: {list(EXPERIMENTS)}")
    for ename, cfg in ex.items():
        if cfg is not None and not isinstance(cfg, dict):
            raise SuiteError(f"{path}: experiments.{ename} must be an object")
        unknown = sorted(set(cfg or {}) - set(EXPERIMENT_KEYS[ename]))
        if unknown:
            raise SuiteError(f"{path}: experiments.{ename} has unknown key(s) {unknown}; "
                             f"known: {list(EXPERIMENT_KEYS[ename])}")
        for cname in (cfg or {}).get("cases") or []:
            if cname not in seen:
                raise SuiteError(f"{path}: experiments.{ename}.cases names unknown case "
                                 f"{cname!r}")
    extra = raw.get("extra_methods", {}) or {}
    if not all(isinstance(v, str) and ":" in v for v in extra.values()):
        raise SuiteError(f"{path}: extra_methods must map names to 'module:function'")
    return Suite(name=str(raw.get("name", path.stem)), path=str(path),
                 variant=str(raw.get("variant", "llvm_ad_mono")), cases=cases,
                 method_options=mo, experiments=ex, extra_methods=extra,
                 description=str(raw.get("description", "")))


# ---------------------------------------------------------------------------- plans
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


def _train_fields() -> set:
    from mi_grg.training.config import TrainConfig
    return {f.name for f in dataclasses.fields(TrainConfig)}


def canonical_options(method: str, options: dict) -> dict:
    """``options`` without entries equal to the method's defaults (so that e.g. gr with
    k=6 and gr with no options are recognised as the same run)."""
    from mi_grg.methods import get_method
    options = dict(options)
    if method in TRAINED:
        from mi_grg.training.config import make_config
        base = make_config(method).to_dict()
        cfg = make_config(method, **{k: v for k, v in options.items() if k in base})
        return {k: v for k, v in options.items()
                if k not in base or cfg.to_dict()[k] != base[k]}
    try:
        params = inspect.signature(get_method(method)).parameters
    except (ValueError, TypeError):
        return options
    return {k: v for k, v in options.items()
            if not (k in params and params[k].default is not inspect.Parameter.empty
                    and params[k].default == v)}


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
            ("r2+deinit", "r2", {"sigma_d": d.sigma_d}, "+ De-Init"),
            ("r2+pga", "r2", {"use_pga": True}, "+ PGA"),
            # the Laplacian alone: with r2+graph it separates the field's effect
            ("r2+lap", "r2", {"lambda_lap": d.lambda_lap}, "+ Laplacian"),
            ("r2+graph", "r2", {"use_graph_field": True, "lambda_lap": d.lambda_lap},
             "+ graph field & Laplacian"),
            ("gr", "gr", {}, "GR-Gaussian (all)")]


def plan_experiment(name: str, suite: Suite, methods=None, cases=None) -> list:
    """The runs of experiment ``name`` on ``suite`` (optionally restricted to ``methods``
    (base method names) and ``cases`` (case names))."""
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
        if want is None or base in want or method in want:
            specs.append(RunSpec(name, case, run, method, options, label or run))

    for case in case_list:
        if name == "table1":
            for m in ecfg.get("methods") or ALL_METHODS:
                add(case, m, m, _opts(suite, m))
                if m in FIXED_ROWS:
                    add(case, f"{m}-fixed", m, _opts(suite, m, **FIXED_ROWS[m]),
                        f"{m} (fixed {FIXED_ROWS[m]['n_iter']} sweeps)")
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


# ---------------------------------------------------------------------------- curve methods
def _curve_method(kind: str):
    """``kind`` ("sart" / "asd-pocs" / "pdhg", a fixed setting) with a per-sweep log of (seconds, 3-D PSNR) written to
    OUT/progress_log.csv; the time spent scoring is excluded from the logged seconds."""
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


# ---------------------------------------------------------------------------- workers
def _worker_setup(variant: str, threads: int | None, extra: dict) -> None:
    import mi_grg
    if mi_grg.variant() != variant:
        mi_grg.set_variant(variant)
    if threads:
        import drjit as dr
        dr.set_thread_count(int(threads))
    register_experiment_methods(extra)


@contextlib.contextmanager
def _logged(path: Path):
    with open(path, "a") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        yield


def simulate_data(case: CaseSpec, data_dir) -> Path:
    """Simulate ``case`` into ``data_dir`` (written to a temporary sibling, then renamed)."""
    from mi_grg.data.dataset import save_case
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=case.n, det=case.det, views=case.views, mode=case.mode)
    test = default_test_angles(case.test_views) if case.test_views else np.zeros(0)
    noise = NoiseModel(**case.noise) if case.noise else None
    if case.is_volume:
        from mi_grg.data.volume_phantom import simulate_volume_case
        c = simulate_volume_case(case.source, geo, test, noise, seed=case.seed,
                                 oversample=case.oversample, ground_truth=case.ground_truth)
    else:
        c = simulate_case(case.source, geo, test, noise, seed=case.seed)
    c.info["suite_case"] = dataclasses.asdict(case)
    data_dir = Path(data_dir)
    tmp = data_dir.with_name(data_dir.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    save_case(c, tmp)
    if data_dir.exists():
        shutil.rmtree(data_dir)
    os.replace(tmp, data_dir)
    return data_dir


def _simulate_task(task: dict) -> dict:
    t0 = time.perf_counter()
    try:
        _worker_setup(task["variant"], task["threads"], task["extra"])
        simulate_data(CaseSpec(**task["case"]), task["data_dir"])
        return {"status": "ok", "seconds": time.perf_counter() - t0}
    except Exception as e:   # recorded; never kills the runner
        err = Path(task["data_dir"]).with_name(Path(task["data_dir"]).name + ".error.txt")
        err.parent.mkdir(parents=True, exist_ok=True)
        err.write_text(traceback.format_exc())
        return {"status": "failed", "error": f"{type(e).__name__}: {e}"}


def _run_task(task: dict) -> dict:
    """Worker body: one reconstruction under the contract; never raises."""
    run_dir = Path(task["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "error.txt").unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        with _logged(run_dir / "log.txt"):
            _worker_setup(task["variant"], task["threads"], task["extra"])
            from mi_grg.data.dataset import load_case
            from mi_grg.methods import get_method, reconstruct
            case = load_case(task["data_dir"])
            opts = dict(task["options"])
            params = inspect.signature(get_method(task["method"])).parameters
            if "progress" in params:
                opts.setdefault("progress", False)
            if "resume" in params and (run_dir / "checkpoint.npz").exists():
                opts["resume"] = True   # continue an interrupted training run
            _, metrics = reconstruct(case, task["method"], out_dir=run_dir, **opts)
        return {"status": "ok", "seconds": metrics["seconds"],
                "psnr_3d": metrics.get("psnr_3d"), "ssim_3d": metrics.get("ssim_3d")}
    except BaseException as e:  # noqa: BLE001 (KeyboardInterrupt in a worker: record it too)
        (run_dir / "error.txt").write_text(traceback.format_exc())
        return {"status": "failed", "error": f"{type(e).__name__}: {e}",
                "seconds": time.perf_counter() - t0}


def _execute(func, tasks: list, jobs: int, desc: str, progress: bool,
             on_result=None) -> list:
    """Run ``func(task)`` for every task in fresh spawned processes, ``jobs`` at a time.

    A worker that dies (segfault, OOM kill) breaks the pool; its unfinished tasks are then
    retried one per pool, so a crashing run only fails itself. ``on_result(i, result)`` is
    called as each task finishes."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool
    from tqdm import tqdm
    results = [None] * len(tasks)
    ctx = mp.get_context("spawn")
    bar = tqdm(total=len(tasks), desc=desc, disable=not progress, dynamic_ncols=True)
    failed = 0

    def record(i, res):
        nonlocal failed
        results[i] = res
        failed += res["status"] != "ok"
        if on_result is not None:
            on_result(i, res)
        bar.update(1)
        bar.set_postfix(failed=failed, refresh=False)

    pending = list(range(len(tasks)))
    rounds = [(pending, jobs)]
    while rounds:
        idx, n = rounds.pop(0)
        broken = []
        with ProcessPoolExecutor(max_workers=max(1, min(n, len(idx))), mp_context=ctx,
                                 max_tasks_per_child=1) as pool:
            futs = {pool.submit(func, tasks[i]): i for i in idx}
            for fut in as_completed(futs):
                i = futs[fut]
                try:
                    record(i, fut.result())
                except BrokenProcessPool:
                    broken.append(i)
                except Exception as e:  # pickling errors etc.
                    record(i, {"status": "failed", "error": f"{type(e).__name__}: {e}"})
        if len(idx) > 1:   # cannot tell which task crashed: retry each alone
            rounds.extend(([i], 1) for i in broken)
        else:
            for i in broken:
                record(i, {"status": "failed", "error": "worker process died (crash or "
                                                        "out of memory)"})
    bar.close()
    return results


def stale_options(run_dir: Path) -> list:
    """Training options of a finished r2/gr run whose values differ from what this code
    resolves the run's options to (a default changed since it ran); [] if none differ or
    the run is not a training run. Such a run is not reused: it is run again."""
    try:
        m = json.loads((Path(run_dir) / "metrics.json").read_text())
    except (OSError, ValueError):
        return []
    return stale_keys(m)


def stale_keys(m: dict) -> list:
    """``stale_options`` for a run's metrics.json already read into ``m``."""
    from mi_grg.training.config import ADDED_LATER, PRESETS, TrainConfig, make_config
    if (m.get("method") in ("sart", "asd-pocs", "pdhg")
            and (m.get("options") or {}).get("stop", "heldout") == "heldout"
            and (m.get("method_info") or {}).get("protocol") != "heldout"):
        return ["stop"]     # ran a fixed sweep count before held-out stopping was the default
    used = (m.get("method_info") or {}).get("config")
    if m.get("method") not in PRESETS or not isinstance(used, dict):
        return []
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    opts = {k: v for k, v in (m.get("options") or {}).items() if k in names}
    try:
        now = make_config(m["method"], (m.get("options") or {}).get("config"), **opts).to_dict()
    except Exception:  # noqa: BLE001 (an option this code no longer accepts)
        return ["config"]
    used = {**ADDED_LATER, **used}      # recorded values win
    return sorted(k for k in set(now) | set(used) if now.get(k) != used.get(k))


def _is_done(run_dir: Path) -> bool:
    return (run_dir / "metrics.json").is_file() and not stale_options(run_dir)


def _index_done(out: Path) -> dict:
    """key -> run_dir of every finished (non-symlinked) run under OUT."""
    index = {}
    for spec_file in out.glob("*/*/*/run_spec.json"):
        d = spec_file.parent
        if d.is_symlink() or not _is_done(d):
            continue
        try:
            key = json.loads(spec_file.read_text())["key"]
        except (OSError, ValueError, KeyError):
            continue
        index.setdefault(key, d)
    return index


def _link(link: Path, target: Path) -> None:
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() or link.is_file():
        link.unlink()
    elif link.exists():
        shutil.rmtree(link)   # an unfinished run replaced by an identical finished one
    os.symlink(os.path.relpath(target, link.parent), link, target_is_directory=True)


def expected_cost(spec: RunSpec, out: Path) -> float:
    """A rough relative cost of a run, to start the longest runs first.

    Trained methods (r2 / gr) cost minutes, the iterative baselines seconds, FDK less.
    A trained run's Gaussians, and with them its time, grow with the occupied part of
    the volume (the cube-filling micro-CT crops took 3-5x the phantoms' time), so its
    cost is 1 + the fraction of ground-truth voxels above 5 % of the maximum (0.5 when
    the data set has no ground truth). Runs without early stopping come first among
    equals, since they run their whole schedule."""
    if spec.method not in TRAINED:
        return {"fdk": 0.0}.get(spec.method, 0.01)
    nostop = spec.options.get("stop_drop") == NOSTOP_DROP
    return 1.0 + _fill_fraction(spec.data_dir(out) / "vol_gt.npy") + 0.01 * nostop


@functools.lru_cache(maxsize=None)
def _fill_fraction(gt: Path) -> float:
    """Fraction of ground-truth voxels above 5 % of the maximum (0.5 without one); read
    once per data set, not once per run on it."""
    if not gt.is_file():
        return 0.5
    v = np.load(gt)
    top = float(np.max(v))
    return float(np.mean(v > 0.05 * top)) if top > 0 else 0.0


def default_jobs(variant: str, n_tasks: int) -> int:
    """One job on a GPU variant (one device), else up to the core count."""
    if variant.startswith("cuda"):
        return 1
    return max(1, min(os.cpu_count() or 1, n_tasks))


def run_experiment(name: str, suite_path, out_dir, jobs: int | None = None, methods=None,
                   dry_run: bool = False, cases=None, progress: bool = True) -> dict:
    """Plan and run experiment ``name`` (or "all") of the suite into ``out_dir``.

    Args:
        name: one of ``EXPERIMENTS`` or "all" (those the suite lists; all if none).
        suite_path: suite JSON file.
        out_dir: results root (layout in the module docstring).
        jobs: parallel worker processes (None: ``default_jobs``).
        methods, cases: optional lists (or comma-separated strings) restricting the runs.
        dry_run: only plan; nothing is simulated or run.
    Returns:
        {"planned", "done_before", "linked", "ran", "failed", "runs": [per-run dicts]}.
    """
    suite = load_suite(suite_path)
    if isinstance(methods, str):
        methods = [m for m in methods.split(",") if m]
    if isinstance(cases, str):
        cases = [c for c in cases.split(",") if c]
    if name == "all":   # the experiments the suite lists (every one if it lists none)
        names = [n for n in EXPERIMENTS if n in suite.experiments] or list(EXPERIMENTS)
    else:
        names = [name]
    specs = [s for n in names for s in plan_experiment(n, suite, methods, cases)]
    out = Path(out_dir)
    index = _index_done(out) if out.exists() else {}
    rows, todo, first_of = [], [], {}
    for s in specs:
        d, key = s.run_dir(out), s.key()
        row = {"experiment": s.experiment, "case": s.case.name, "run": s.run,
               "category": s.case.category, "label": s.label, "views": s.case.views,
               "method": s.method, "options": s.options, "dir": str(d)}
        if (d / "metrics.json").is_file() and not _is_done(d):
            row["stale"] = stale_options(d)   # defaults changed since it ran: run again
        if _is_done(d):
            row["status"] = "done before"
        elif key in index:
            row["status"], row["target"] = "linked", str(index[key])
        elif key in first_of:
            row["status"], row["target"] = "duplicate", str(first_of[key].run_dir(out))
        else:
            row["status"] = "todo"
            first_of[key] = s
            todo.append(s)
        rows.append(row)
    datas = {}
    for s in todo:
        if not (s.data_dir(out) / "meta_data.json").is_file():
            datas[s.case.data_dir_name] = s.case
    summary = {"experiment": name, "suite": suite.path, "planned": len(specs),
               "to_simulate": sorted(datas), "runs": rows}
    if dry_run:
        summary.update({k: sum(r["status"] == k for r in rows)
                        for k in ("done before", "linked", "duplicate", "todo")})
        return summary

    out.mkdir(parents=True, exist_ok=True)
    (out / "suite.json").write_text(Path(suite.path).read_text())
    n_jobs = jobs or default_jobs(suite.variant, max(len(todo), len(datas), 1))
    cores = os.cpu_count() or 1

    def base_task(n_parallel):
        return {"variant": suite.variant, "extra": suite.extra_methods,
                "threads": max(1, cores // max(1, n_parallel))
                if suite.variant.startswith("llvm") else None}

    sim_failed = set()
    if datas:
        tasks = [{**base_task(min(n_jobs, len(datas))), "case": dataclasses.asdict(c),
                  "data_dir": str(out / "data" / dn)} for dn, c in datas.items()]
        res = _execute(_simulate_task, tasks, n_jobs, "simulate", progress)
        sim_failed = {dn for dn, r in zip(datas, res) if r["status"] != "ok"}
    for s in todo:   # write specs first: a run in progress is recognisable on disk
        d = s.run_dir(out)
        if d.is_symlink():            # linked to a run that is stale now: run it here
            d.unlink()
        for old in ("metrics.json", "checkpoint.npz"):   # a stale run starts afresh
            (d / old).unlink(missing_ok=True)
        d.mkdir(parents=True, exist_ok=True)
        (d / "run_spec.json").write_text(json.dumps({**s.to_dict(), "key": s.key()},
                                                    indent=2, default=str))
    runnable = [s for s in todo if s.case.data_dir_name not in sim_failed]
    # Longest first, so that no long run starts last and leaves the other workers idle.
    runnable.sort(key=lambda s: -expected_cost(s, out))
    tasks = [{**base_task(min(n_jobs, len(runnable))), "run_dir": str(s.run_dir(out)),
              "data_dir": str(s.data_dir(out)), "method": s.method, "options": s.options}
             for s in runnable]
    row_of = {s.key(): (s, row) for s, row in zip(specs, rows) if row["status"] == "todo"}

    def finish(key, r):
        s, row = row_of[key]
        row.update({"status": "ran" if r["status"] == "ok" else "failed",
                    **{k: v for k, v in r.items() if k != "status"}})
        err = s.run_dir(out) / "error.txt"
        if r["status"] != "ok" and not err.exists():   # the worker died before writing
            err.write_text(str(r.get("error")) + "\n")

    def write_index(final: bool) -> None:
        # While runs go on, only finished rows are written: a killed runner leaves a
        # runs.json of everything that completed (the report reads it as it is).
        for n in names:
            mine = [r for r in rows if r["experiment"] == n
                    and (final or r["status"] in ("done before", "ran", "failed"))]
            if mine or final:
                _write_runs_json(out / n, n, suite, mine,
                                 experiment_command(n, suite.path, out, methods, cases), n_jobs)

    def on_result(i, r):
        finish(runnable[i].key(), r)
        write_index(final=False)

    if tasks:
        _execute(_run_task, tasks, n_jobs, name, progress, on_result=on_result)
    for s in todo:
        if s.case.data_dir_name in sim_failed:
            msg = f"simulation of data {s.case.data_dir_name} failed (see data/*.error.txt)"
            (s.run_dir(out) / "error.txt").write_text(msg + "\n")
            finish(s.key(), {"status": "failed", "error": msg})
    for s, row in zip(specs, rows):
        if row["status"] in ("linked", "duplicate"):
            target = Path(row["target"])
            if _is_done(target):
                _link(s.run_dir(out), target)
                row["status"] = "linked"
            else:
                row["status"] = "failed"
                row["error"] = f"identical run {target} failed"
    write_index(final=True)
    summary.update({k: sum(r["status"] == k for r in rows)
                    for k in ("done before", "linked", "ran", "failed")})
    return summary


def _write_runs_json(exp_dir: Path, name: str, suite: Suite, rows: list, command: str,
                     jobs: int) -> None:
    """Merge ``rows`` into EXP/runs.json (runs of earlier invocations with other
    --methods / --cases filters are kept; the same (case, run) is replaced)."""
    exp_dir.mkdir(parents=True, exist_ok=True)
    path = exp_dir / "runs.json"
    old = {}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except ValueError:
            old = {}
    merged = {(r["case"], r["run"]): r for r in old.get("runs", [])}
    merged.update({(r["case"], r["run"]): r for r in rows})
    commands = [c for c in old.get("commands", []) if c != command] + [command]
    path.write_text(json.dumps(
        {"experiment": name, "suite": suite.path, "suite_name": suite.name,
         "variant": suite.variant, "commands": commands, "jobs": jobs,
         "finished": time.strftime("%Y-%m-%d %H:%M:%S"), "runs": list(merged.values())},
        indent=2, default=str))


def experiment_command(name, suite_path, out, methods=None, cases=None) -> str:
    cmd = f"mi-grg experiment {name} --suite {suite_path} --out {out}"
    if methods:
        cmd += f" --methods {','.join(methods)}"
    if cases:
        cmd += f" --cases {','.join(cases)}"
    return cmd


# ---------------------------------------------------------------------------- CLI
def add_experiment_parser(subparsers) -> None:
    """Add the ``experiment`` and ``report`` sub-commands to an argparse subparsers."""
    e = subparsers.add_parser("experiment", help="run a scripted experiment of a suite",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("name", choices=(*EXPERIMENTS, "all"))
    e.add_argument("--suite", required=True, help="suite JSON (experiments/suite_cpu.json)")
    e.add_argument("--out", required=True, help="results directory")
    e.add_argument("--jobs", type=int, help="parallel runs (default: cores; 1 on a GPU)")
    e.add_argument("--methods", help="comma-separated methods to keep (e.g. fdk,sart)")
    e.add_argument("--cases", help="comma-separated case names to keep")
    e.add_argument("--dry-run", action="store_true", help="print the plan, run nothing")
    e.set_defaults(func=cmd_experiment)
    r = subparsers.add_parser("report", help="write docs/results.md from a results directory")
    r.add_argument("--out", required=True, help="results directory (as given to experiment)")
    r.add_argument("--report", default="docs/results.md", help="markdown file to write")
    r.set_defaults(func=cmd_report)


def cmd_experiment(args) -> int:
    res = run_experiment(args.name, args.suite, args.out, jobs=args.jobs,
                         methods=args.methods, cases=args.cases, dry_run=args.dry_run)
    if args.dry_run:
        for r in res["runs"]:
            extra = f" -> {r['target']}" if "target" in r else ""
            if r.get("stale"):
                extra += f" (ran with other defaults: {', '.join(r['stale'])})"
            print(f"{r['status']:12s} {r['experiment']}/{r['case']}/{r['run']}  "
                  f"[{r['method']} {json.dumps(r['options'])}]{extra}")
        print(f"{res['planned']} runs: {res.get('todo', 0)} to run, "
              f"{res.get('done before', 0)} done, {res.get('linked', 0) + res.get('duplicate', 0)}"
              f" shared; data to simulate: {', '.join(res['to_simulate']) or 'none'}")
        return 0
    print(f"{res['planned']} runs: {res['ran']} ran, {res['failed']} failed, "
          f"{res['done before']} done before, {res['linked']} linked -> {args.out}")
    for r in res["runs"]:
        if r["status"] == "failed":
            print(f"  FAILED {r['experiment']}/{r['case']}/{r['run']}: {r.get('error')}")
    return 1 if res["failed"] else 0


def cmd_report(args) -> int:
    from mi_grg.lab.report import write_report
    path = write_report(args.out, args.report)
    print(f"wrote {path}")
    return 0


def main(argv=None) -> int:
    """``python -m mi_grg.lab.experiments experiment|report ...`` (same as ``mi-grg``)."""
    p = argparse.ArgumentParser(prog="python -m mi_grg.lab.experiments")
    add_experiment_parser(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
