"""Scripted experiments: a suite of cases (JSON), the paper's experiments as run plans, and a
resumable, parallel runner.

    mi-grg experiment NAME --suite experiments/suite_cpu.json --out results/cpu [--jobs N]
                           [--methods a,b] [--cases x,y] [--dry-run]
                           [--dask tcp://HOST:8786] [--threads-per-run T]
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
resolves its options to (a default changed since: ``stale_options``; where only options
that act after training changed, the run resumes from its final checkpoint and redoes only
the result's steps, else it starts afresh); a run identical to
one done elsewhere in OUT (same data, method and options) becomes a relative symlink to it
instead of running again; a trained run that differs from another of the same data and
method only after training (gr-paper beside gr) shares its training: it runs after it, from
its final checkpoint, and redoes only the result's steps (its time counts the training).
``OUT/<experiment>/runs.json`` is rewritten as runs finish.

Runs execute in spawned worker processes (Dr.Jit is not fork-safe), one fresh process per
run, ``jobs`` at a time, each with ``cores // jobs`` Dr.Jit threads. A failing run writes
error.txt and does not stop the others. With ``--dask`` they are tasks on a Dask cluster
instead, OUT shared with its workers (``mi_grg.lab.cluster``; experiments/README.md).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import json
import os
import shutil
import socket
import threading
import time
import traceback
from pathlib import Path

import numpy as np

from mi_grg.lab.curves import register_experiment_methods
from mi_grg.lab.plan import RunSpec, check_method_filter, plan_experiment
from mi_grg.lab.reuse import plan_rows, resolve_duplicates, take_twin_checkpoint, write_specs
from mi_grg.lab.suite import EXPERIMENTS, NOSTOP_DROP, TRAINED, CaseSpec, Suite, load_suite


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


def suite_case(case: CaseSpec, root):
    """The Case of suite case ``case``, from ``root`` / its data folder, simulated there
    first when missing (benchmarks that run outside the runner's plan)."""
    from mi_grg.data.dataset import load_case
    d = Path(root) / case.data_dir_name
    if not (d / "meta_data.json").exists():
        simulate_data(case, d)
    return load_case(d)


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
             on_result=None, client=None) -> list:
    """Run ``func(task)`` for every task: in fresh spawned processes here, ``jobs`` at a
    time, or, given a ``distributed.Client``, one Dask task each on its cluster
    (``mi_grg.lab.cluster``). ``on_result(i, result)`` is called, in this process, as each
    task finishes; a task that cannot finish is a failed result, never an exception."""
    from tqdm import tqdm
    results = [None] * len(tasks)
    bar = tqdm(total=len(tasks), desc=desc, disable=not progress, dynamic_ncols=True)
    failed = 0
    if client is None:
        finished = _run_local(func, tasks, jobs)
    else:
        from mi_grg.lab.cluster import run_on_cluster
        counted = [{**t, "attempts_file": str(_attempts_file(t))} for t in tasks]
        finished = run_on_cluster(client, func, counted, desc)
    for i, res in finished:
        results[i] = res
        failed += res["status"] != "ok"
        if on_result is not None:
            on_result(i, res)
        bar.update(1)
        bar.set_postfix(failed=failed, refresh=False)
    bar.close()
    return results


def _stop_with_runner(runner_pid: int, poll_s: float = 1.0) -> None:
    """Worker initializer: a worker whose runner is gone (killed, not interrupted: SIGTERM
    reaches the runner alone) exits, instead of training on beside the next runner in the
    same run folder; its last checkpoint stays there for that runner to resume."""
    def watch():
        while os.getppid() == runner_pid:
            time.sleep(poll_s)
        os._exit(3)
    threading.Thread(target=watch, name="stop-with-runner", daemon=True).start()


def _run_local(func, tasks: list, jobs: int):
    """Yield (i, func(tasks[i])) as tasks finish in fresh spawned processes, ``jobs`` at a
    time. A worker that dies (segfault, OOM kill) breaks the pool; its unfinished tasks are
    then retried one per pool, so a crashing run only fails itself. Workers stop when this
    process dies (``_stop_with_runner``)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool
    ctx = mp.get_context("spawn")
    rounds = [(list(range(len(tasks))), jobs)]
    while rounds:
        idx, n = rounds.pop(0)
        broken = []
        with ProcessPoolExecutor(max_workers=max(1, min(n, len(idx))), mp_context=ctx,
                                 max_tasks_per_child=1, initializer=_stop_with_runner,
                                 initargs=(os.getpid(),)) as pool:
            futs = {pool.submit(func, tasks[i]): i for i in idx}
            for fut in as_completed(futs):
                i = futs[fut]
                try:
                    yield i, fut.result()
                except BrokenProcessPool:
                    broken.append(i)
                except Exception as e:  # pickling errors etc.
                    yield i, {"status": "failed", "error": f"{type(e).__name__}: {e}"}
        if len(idx) > 1:   # cannot tell which task crashed: retry each alone
            rounds.extend(([i], 1) for i in broken)
        else:
            for i in broken:
                yield i, {"status": "failed",
                          "error": "worker process died (crash or out of memory)"}


def _attempts_file(task: dict) -> Path:
    """Where a cluster task counts its starts: in the run's directory, or beside the data
    set it simulates."""
    if "run_dir" in task:
        return Path(task["run_dir"]) / "attempts.txt"
    data = Path(task["data_dir"])
    return data.with_name(data.name + ".attempts.txt")


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
                   dry_run: bool = False, cases=None, progress: bool = True,
                   dask: str | None = None, threads_per_run: int | None = None) -> dict:
    """Plan and run experiment ``name`` (or "all") of the suite into ``out_dir``.

    Args:
        name: one of ``EXPERIMENTS`` or "all" (those the suite lists; all if none).
        suite_path: suite JSON file.
        out_dir: results root (layout in the module docstring).
        jobs: parallel worker processes (None: ``default_jobs``).
        methods, cases: optional lists (or comma-separated strings) restricting the runs.
        dry_run: only plan; nothing is simulated or run.
        dask: address of a Dask scheduler (``tcp://host:8786``): the data sets and then the
            runs are Dask tasks on its cluster (``mi_grg.lab.cluster``) instead of local
            processes; OUT must be on a file system the workers share.
        threads_per_run: Dr.Jit threads of each run (LLVM variant; default: cores // jobs
            here, 1 on a cluster).
    Returns:
        {"planned", "done_before", "linked", "ran", "failed", "runs": [per-run dicts]}.
    """
    suite = load_suite(suite_path)
    methods, cases = _as_list(methods), _as_list(cases)
    if name == "all":   # the experiments the suite lists (every one if it lists none)
        names = [n for n in EXPERIMENTS if n in suite.experiments] or list(EXPERIMENTS)
    else:
        names = [name]
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    specs = [s for n in names for s in plan_experiment(n, suite, methods, cases)]
    check_method_filter(names, suite, methods, specs)
    # the workers of a cluster may start elsewhere: they get absolute paths
    out = Path(out_dir).absolute() if dask else Path(out_dir)
    rows, todo = plan_rows(specs, out)
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

    if threads_per_run is not None and threads_per_run < 1:
        raise ValueError(f"threads_per_run must be >= 1, got {threads_per_run}")
    client = None
    if dask:
        if jobs is not None:
            raise ValueError("jobs sets the local worker processes; with dask the cluster's "
                             "workers run the tasks (leave jobs out)")
        from mi_grg.lab.cluster import connect
        client = connect(dask)     # before anything is written: an unreachable one leaves none
    # closed on the way out, failure or not (the cluster's queued tasks are cancelled)
    with client if client is not None else contextlib.nullcontext(), _one_runner(out):
        (out / "suite.json").write_text(Path(suite.path).read_text())
        if client is None:
            n_jobs = jobs or default_jobs(suite.variant, max(len(todo), len(datas), 1))
            where = {"jobs": n_jobs}
        else:
            n_jobs = None
            where = {"dask": str(dask), "threads_per_run": threads_per_run or 1}
        inv = _Invocation(name, names, suite, out, methods, cases, progress, client, n_jobs,
                          where, threads_per_run)
        sim_failed = inv.simulate(datas)
        write_specs(todo, rows, out)
        inv.run(todo, specs, rows, sim_failed)
        resolve_duplicates(specs, rows, out)
        inv.write_index(rows, final=True)
        summary.update({k: sum(r["status"] == k for r in rows)
                        for k in ("done before", "linked", "ran", "failed")})
        return summary


RUNNER_FILE = ".runner.pid"


@contextlib.contextmanager
def _one_runner(out: Path):
    """One runner at a time in ``out``: a second would run the same runs into the same
    folders. ``out`` is made; ``out/.runner.pid`` names the running one (host and pid); a
    runner that died on this host is taken over; one on another host (a shared file
    system) must be ended there, or its file removed by hand."""
    from mi_grg.data.outputs import _alive
    out.mkdir(parents=True, exist_ok=True)
    path, host = out / RUNNER_FILE, socket.gethostname()
    me = f"{host} {os.getpid()}"
    for _ in range(5):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                other_host, other_pid = path.read_text().split()
                other_pid = int(other_pid)
            except (OSError, ValueError):   # gone, or half-written by a runner starting now
                time.sleep(0.2)
                continue
            if other_host != host or _alive(other_pid):
                raise ValueError(
                    f"--out {out}: another `mi-grg experiment` (pid {other_pid} on "
                    f"{other_host}) is running there; wait for it or stop it (if none runs, "
                    f"remove {path})")
            path.unlink(missing_ok=True)    # a dead runner's
            continue
        with os.fdopen(fd, "w") as f:
            f.write(me)
        break
    else:
        raise ValueError(f"--out {out}: cannot take {path} (a runner starting now, or a "
                         "damaged file: remove it if none runs)")
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            if path.read_text() == me:
                path.unlink()


def _as_list(values):
    """A comma-separated string as a list (None and lists unchanged)."""
    if isinstance(values, str):
        return [v for v in values.split(",") if v]
    return values


@dataclasses.dataclass
class _Invocation:
    """What the steps of one ``run_experiment`` call share: where and how tasks run."""
    name: str
    names: list
    suite: Suite
    out: Path
    methods: list | None
    cases: list | None
    progress: bool
    client: object
    n_jobs: int | None
    where: dict
    threads_per_run: int | None

    def base_task(self, n_parallel: int) -> dict:
        """The task fields every worker gets: variant, extra methods, Dr.Jit threads."""
        cores = os.cpu_count() or 1
        threads = self.threads_per_run or (1 if self.client is not None
                                           else max(1, cores // max(1, n_parallel)))
        return {"variant": self.suite.variant, "extra": self.suite.extra_methods,
                "threads": threads if self.suite.variant.startswith("llvm") else None}

    def simulate(self, datas: dict) -> set:
        """Simulate the missing data sets; returns the names of those that failed."""
        if not datas:
            return set()
        tasks = [{**self.base_task(min(self.n_jobs or 1, len(datas))),
                  "case": dataclasses.asdict(c), "data_dir": str(self.out / "data" / dn)}
                 for dn, c in datas.items()]
        res = _execute(_simulate_task, tasks, self.n_jobs, "simulate", self.progress,
                       client=self.client)
        return {dn for dn, r in zip(datas, res) if r["status"] != "ok"}

    def write_index(self, rows: list, final: bool) -> None:
        """Each experiment's runs.json. While runs go on, only finished rows are written:
        a killed runner leaves a runs.json of everything that completed (the report reads
        it as it is)."""
        for n in self.names:
            mine = [r for r in rows if r["experiment"] == n
                    and (final or r["status"] in ("done before", "ran", "failed"))]
            if mine or final:
                command = experiment_command(n, self.suite.path, self.out, self.methods,
                                             self.cases)
                _write_runs_json(self.out / n, n, self.suite, mine, command, self.where)

    def run(self, todo: list, specs: list, rows: list, sim_failed: set) -> None:
        """Run the runs whose data exist, longest first; record each result in its row."""
        out = self.out
        row_of = {s.key(): (s, row) for s, row in zip(specs, rows) if row["status"] == "todo"}
        runnable = [s for s in todo if s.case.data_dir_name not in sim_failed]
        # Runs that share a twin's training go after it (a second wave), from its checkpoint.
        later = [s for s in runnable if row_of[s.key()][1].get("waits")]
        for s in runnable:
            if s not in later and row_of[s.key()][1].get("trains_with"):
                take_twin_checkpoint(s, row_of[s.key()][1], out)
        self._run_wave([s for s in runnable if s not in later], row_of, rows)
        for s in later:
            take_twin_checkpoint(s, row_of[s.key()][1], out)
        self._run_wave(later, row_of, rows)
        for s in todo:
            if s.case.data_dir_name in sim_failed:
                msg = f"simulation of data {s.case.data_dir_name} failed (see data/*.error.txt)"
                (s.run_dir(out) / "error.txt").write_text(msg + "\n")
                self._finish(row_of, s.key(), {"status": "failed", "error": msg})

    def _finish(self, row_of: dict, key: str, r: dict) -> None:
        s, row = row_of[key]
        row.update({"status": "ran" if r["status"] == "ok" else "failed",
                    **{k: v for k, v in r.items() if k != "status"}})
        err = s.run_dir(self.out) / "error.txt"
        if r["status"] != "ok" and not err.exists():   # the worker died before writing
            err.write_text(str(r.get("error")) + "\n")

    def _run_wave(self, runnable: list, row_of: dict, rows: list) -> None:
        """Run ``runnable`` at once, longest first; record each result in its row."""
        out = self.out
        # Longest first, so that no long run starts last and leaves the other workers idle.
        runnable = sorted(runnable, key=lambda s: -expected_cost(s, out))
        tasks = [{**self.base_task(min(self.n_jobs or 1, len(runnable))),
                  "run_dir": str(s.run_dir(out)), "data_dir": str(s.data_dir(out)),
                  "method": s.method, "options": s.options} for s in runnable]

        def on_result(i, r):
            self._finish(row_of, runnable[i].key(), r)
            self.write_index(rows, final=False)

        if tasks:
            _execute(_run_task, tasks, self.n_jobs, self.name, self.progress,
                     on_result=on_result, client=self.client)


def _write_runs_json(exp_dir: Path, name: str, suite: Suite, rows: list, command: str,
                     where: dict) -> None:
    """Merge ``rows`` into EXP/runs.json (runs of earlier invocations with other
    --methods / --cases filters are kept; the same (case, run) is replaced). ``where`` says
    where they ran: {"jobs": N} here, {"dask": address, "threads_per_run": T} on a cluster."""
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
         "variant": suite.variant, "commands": commands, **where,
         "finished": time.strftime("%Y-%m-%d %H:%M:%S"), "runs": list(merged.values())},
        indent=2, default=str))


def experiment_command(name, suite_path, out, methods=None, cases=None) -> str:
    cmd = f"mi-grg experiment {name} --suite {suite_path} --out {out}"
    if methods:
        cmd += f" --methods {','.join(methods)}"
    if cases:
        cmd += f" --cases {','.join(cases)}"
    return cmd

