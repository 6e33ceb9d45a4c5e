"""The experiment runner on a Dask cluster (mi_grg.lab.cluster): a ``distributed.LocalCluster``
of 2 worker processes with 1 thread each gives the local runner's results; a worker killed
mid-run loses only its run, which is resubmitted (at most twice); an unreachable scheduler
is one line and exit status 2, with nothing written."""
import json
import logging
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from mi_grg.cli import main
from mi_grg.lab.cluster import MAX_STARTS, _counted
from mi_grg.lab.runner import run_experiment

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "experiments" / "suite_smoke.json"


def dies_once(case, marker: str = "", **options):
    """A test method (imported by the workers via extra_methods): kills its worker process
    the first time (``marker`` does not exist yet), returns zeros after that."""
    if not Path(marker).exists():
        Path(marker).write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return np.zeros(case.geometry.nVoxel, np.float32)


def dies_always(case, **options):
    """A test method that kills its worker process every time."""
    os.kill(os.getpid(), signal.SIGKILL)


@pytest.fixture(scope="module")
def cluster():
    from distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL) as c:
        yield c


def _metrics(out, case, run):
    return json.loads((Path(out) / "table1" / case / run / "metrics.json").read_text())


def _runs(out):
    return json.loads((Path(out) / "table1" / "runs.json").read_text())


def _same_results(out_local, out_dask, methods, psnr_tol):
    for case in ("shepp", "needles"):
        for run in methods:
            a, b = _metrics(out_local, case, run), _metrics(out_dask, case, run)
            assert b["psnr_3d"] == pytest.approx(a["psnr_3d"], abs=psnr_tol), (case, run)
            assert b["ssim_3d"] == pytest.approx(a["ssim_3d"], abs=psnr_tol / 100), (case, run)
            if psnr_tol < 1e-5:      # same code, same thread count: the same volume
                np.testing.assert_allclose(
                    np.load(Path(out_dask) / "table1" / case / run / "vol_pred.npy"),
                    np.load(Path(out_local) / "table1" / case / run / "vol_pred.npy"),
                    atol=1e-6)


def _check_cluster_run(out, cluster, res, n_runs):
    assert res["ran"] == n_runs and res["failed"] == 0
    index = _runs(out)
    assert index["dask"] == cluster.scheduler_address and index["threads_per_run"] == 1
    assert all(Path(r["dir"]).is_absolute() for r in index["runs"])
    assert "jobs" not in index and {r["status"] for r in index["runs"]} == {"ran"}
    # simulated once, before the runs, by the cluster; no start counters left behind
    for case in ("shepp", "needles"):
        assert (out / "data" / case / "meta_data.json").is_file()
        assert _metrics(out, case, "fdk")["n_train_views"] == 16
    assert not list(out.rglob("*attempts.txt"))


def test_cluster_matches_local_runner(cluster, tmp_path):
    """The smoke suite's classical runs (2 cases x fdk, sart, asd-pocs, each iterative one
    also with its fixed-sweep row, ASD-POCS also with its best-weight row: 12 runs), locally (2 processes, 1 thread each) and on the
    cluster (2 workers, 1 thread each): the same volumes, hence the same metrics."""
    methods = ("fdk", "sart", "asd-pocs")
    local = run_experiment("table1", SMOKE, tmp_path / "local", jobs=2, methods=methods,
                           progress=False)
    assert local["ran"] == 12 and local["failed"] == 0
    out = tmp_path / "dask"
    res = run_experiment("table1", SMOKE, out, methods=methods, progress=False,
                         dask=cluster.scheduler_address)
    _check_cluster_run(out, cluster, res, 12)
    _same_results(tmp_path / "local", out, methods, psnr_tol=1e-6)
    # a finished run is not rerun on the cluster either
    before = {p: p.stat().st_mtime_ns for p in out.glob("table1/*/*/metrics.json")}
    again = run_experiment("table1", SMOKE, out, methods=methods, progress=False,
                           dask=cluster.scheduler_address)
    assert again["ran"] == 0 and again["done before"] == 12
    assert {p: p.stat().st_mtime_ns for p in out.glob("table1/*/*/metrics.json")} == before


@pytest.mark.slow
def test_smoke_suite_on_cluster_matches_local(cluster, tmp_path):
    """The whole smoke suite (with r2's short training) on both runners."""
    methods = ("fdk", "sart", "asd-pocs", "r2")
    t0 = time.perf_counter()
    local = run_experiment("table1", SMOKE, tmp_path / "local", jobs=2, progress=False)
    assert local["ran"] == 14 and local["failed"] == 0
    assert time.perf_counter() - t0 < 600   # loose: the test machine is shared (1 CPU-min in all)
    out = tmp_path / "dask"
    res = run_experiment("table1", SMOKE, out, progress=False,
                         dask=cluster.scheduler_address)
    _check_cluster_run(out, cluster, res, 14)
    # r2: float atomics may sum in another order; the classical runs are bitwise the same
    _same_results(tmp_path / "local", out, methods, psnr_tol=0.05)


def _kill_suite(tmp_path, methods, marker=None) -> Path:
    raw = json.loads(SMOKE.read_text())
    raw["cases"] = [dict(raw["cases"][0], n=16, det=24, views=4, test_views=2)]
    raw["extra_methods"] = {"dies_once": "test_cluster:dies_once",
                            "dies_always": "test_cluster:dies_always"}
    raw["method_options"] = {"dies_once": {"marker": str(marker)}} if marker else {}
    raw["experiments"] = {"table1": {"methods": list(methods)}}
    path = tmp_path / "kill.json"
    path.write_text(json.dumps(raw))
    return path


def test_killed_worker_loses_only_its_run(cluster, tmp_path, monkeypatch):
    """A worker killed mid-run (the dies_once method kills its own worker process): the
    run is resubmitted and finishes; the run beside it is unaffected; runs.json records
    both as ran."""
    marker = tmp_path / "died"
    suite = _kill_suite(tmp_path, ("dies_once", "fdk"), marker)
    monkeypatch.chdir(tmp_path)                   # a relative OUT: the workers get it absolute
    out = tmp_path / "out"
    res = run_experiment("table1", suite, "out", progress=False,
                         dask=cluster.scheduler_address)
    assert marker.is_file()                                 # a worker did die running it
    assert res["ran"] == 2 and res["failed"] == 0, res["runs"]
    status = {r["run"]: r["status"] for r in _runs(out)["runs"]}
    assert status == {"dies_once": "ran", "fdk": "ran"}
    assert (out / "table1" / "shepp" / "dies_once" / "metrics.json").is_file()


def test_run_that_always_kills_its_worker_fails_after_two_resubmissions(cluster, tmp_path):
    suite = _kill_suite(tmp_path, ("dies_always", "fdk"))
    out = tmp_path / "out"
    res = run_experiment("table1", suite, out, progress=False, dask=cluster.scheduler_address)
    assert res["ran"] == 1 and res["failed"] == 1
    row = {r["run"]: r for r in _runs(out)["runs"]}["dies_always"]
    assert row["status"] == "failed"
    assert f"its worker died {MAX_STARTS} times" in row["error"]
    assert "died" in (out / "table1" / "shepp" / "dies_always" / "error.txt").read_text()


def test_start_counter_caps_the_starts(tmp_path):
    """Worker side: a task started MAX_STARTS times already is not run again; otherwise it
    runs and its counter is removed once it returns."""
    calls = []
    task = {"attempts_file": str(tmp_path / "run" / "attempts.txt")}
    assert _counted(lambda t: calls.append(t) or {"status": "ok"}, task) == {"status": "ok"}
    assert calls == [task] and not Path(task["attempts_file"]).exists()
    Path(task["attempts_file"]).write_text("".join(f"host pid {i}\n" for i in range(MAX_STARTS)))
    res = _counted(lambda t: calls.append(t) or {"status": "ok"}, task)
    assert res["status"] == "failed" and f"died {MAX_STARTS} times" in res["error"]
    assert "host pid 2" in res["error"] and len(calls) == 1


def test_unreachable_scheduler(tmp_path, capsys):
    """One line naming the address and the error, exit 2, well within 10 s; nothing written
    (no OUT, so no partial runs.json)."""
    out = tmp_path / "out"
    for address in ("tcp://127.0.0.1:1", "tcp://no-such-host.invalid:8786"):
        t0 = time.perf_counter()
        rc = main(["experiment", "table1", "--suite", str(SMOKE), "--out", str(out),
                   "--dask", address])
        assert time.perf_counter() - t0 < 10
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1, err
        assert err.startswith(f"mi-grg experiment: error: cannot reach the Dask scheduler at "
                              f"{address}: ")
        assert not out.exists()
    # --jobs is for local runs: with --dask it is an error, not ignored
    assert main(["experiment", "table1", "--suite", str(SMOKE), "--out", str(out),
                 "--dask", "tcp://127.0.0.1:1", "--jobs", "2"]) == 2
    assert "jobs" in capsys.readouterr().err and not out.exists()
