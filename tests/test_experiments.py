"""mi_grg.lab (suite, plan, runner, report) end to end on a tiny suite (16^3, 9 views, fdk + sart):
resumability, parallel = serial, failure isolation, and a report whose numbers are read back
independently from metrics.json."""
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import mi_grg
from mi_grg.training.config import make_config
from mi_grg.lab.plan import plan_experiment
from mi_grg.lab.report import PAPER_TABLE1, load_runs, seeds_table, summary_lines, write_report
from mi_grg.protocol.early_stop import replay
from mi_grg.lab.reuse import stale_options
from mi_grg.lab.runner import expected_cost, run_experiment
from mi_grg.lab.suite import EXPERIMENTS, SuiteError, load_suite

REPO = Path(__file__).resolve().parents[1]


def flaky_method(case, **options):
    """A test method (imported by the spawned workers via the suite's extra_methods): fails
    on the 'blob' case, returns zeros elsewhere."""
    if case.info.get("suite_case", {}).get("name") == "blob":
        raise RuntimeError("deliberate failure for the test")
    return np.zeros(case.geometry.nVoxel, np.float32)


def _suite(tmp: Path, extra=None, methods=("fdk", "sart")) -> Path:
    x = -1 + (np.arange(20) + 0.5) / 10
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    np.save(tmp / "blob.npy", ((X ** 2 + (Y / 0.6) ** 2 + Z ** 2) < 0.5).astype(np.float32) * .8)
    common = {"views": 9, "test_views": 2, "n": 16, "det": 24, "mode": "cone"}
    suite = {"name": "tiny", "variant": "llvm_ad_mono",
             "method_options": {"sart": {"n_iter": 2}},
             "experiments": {"table1": {"methods": list(methods)}},
             "cases": [{"name": "shepp", "category": "HO", "source": "shepp", **common,
                        "noise": {"I0": 1e4, "electronic_std": 10.0}, "seed": 0},
                       {"name": "blob", "category": "AO", "source": str(tmp / "blob.npy"),
                        **common, "noise": None, "seed": 0}]}
    if extra:
        suite["extra_methods"] = extra
    path = tmp / ("suite_extra.json" if extra else "suite.json")
    path.write_text(json.dumps(suite))
    return path


def _tiny_gr_suite(tmp: Path, iterations: int) -> Path:
    """One case (shepp), Table 1's gr rows, a few iterations without held-out views."""
    suite = _suite(tmp, methods=("gr",))
    raw = json.loads(suite.read_text())
    raw["cases"] = raw["cases"][:1]
    raw["method_options"] = {"gr": {"iterations": iterations, "n_points": 300,
                                    "holdout_every": 0}}
    suite.write_text(json.dumps(raw))
    return suite


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("exp")
    suite = _suite(tmp)
    out = tmp / "out1"
    res = run_experiment("table1", suite, out, jobs=1, progress=False)
    return tmp, suite, out, res


@pytest.fixture(scope="module")
def parallel(serial):
    tmp = serial[0]
    suite = _suite(tmp, extra={"flaky": "test_experiments:flaky_method"},
                   methods=("fdk", "sart", "flaky"))
    out = tmp / "out2"
    res = run_experiment("table1", suite, out, jobs=2, progress=False)
    return suite, out, res


def _metrics(out, case, run):
    return json.loads((Path(out) / "table1" / case / run / "metrics.json").read_text())


def test_table1_runs_and_data(serial):
    tmp, suite, out, res = serial
    assert res["ran"] == 6 and res["failed"] == 0      # fdk, sart, sart-fixed x 2 cases
    for case in ("shepp", "blob"):
        gt = np.load(out / "data" / case / "vol_gt.npy")
        for run in ("fdk", "sart"):
            d = out / "table1" / case / run
            for f in ("metrics.json", "vol_pred.npy", "slices.png", "run_spec.json"):
                assert (d / f).is_file(), d / f
            m = _metrics(out, case, run)
            pred = np.load(d / "vol_pred.npy")
            psnr = 10 * np.log10(1.0 / np.mean((pred.astype(np.float64) - gt) ** 2))
            assert m["psnr_3d"] == pytest.approx(psnr, abs=1e-6)
            assert m["nVoxel"] == [16, 16, 16] and m["n_train_views"] == 9
    assert _metrics(out, "shepp", "sart")["options"]["n_iter"] == 2
    # sart stops on held-out views; the fixed row runs the paper's sweeps
    assert _metrics(out, "shepp", "sart")["method_info"]["protocol"] == "heldout"
    fixed = _metrics(out, "shepp", "sart-fixed")["options"]
    assert fixed["n_iter"] == 10 and fixed["stop"] == "none"
    # the data are what the suite says: same as simulating directly
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=16, det=24, views=9)
    direct = simulate_case("shepp", geo, default_test_angles(2), NoiseModel(1e4, 10.0), seed=0)
    case = mi_grg.load_case(out / "data" / "shepp")
    np.testing.assert_allclose(case.train, direct.train, atol=1e-6)
    np.testing.assert_allclose(case.vol_gt, direct.vol_gt, atol=1e-7)
    blob = mi_grg.load_case(out / "data" / "blob")
    assert blob.info["source"] == "mi_grg.data.volume_phantom"


def test_rerun_does_no_work(serial):
    tmp, suite, out, _ = serial
    before = {p: p.stat().st_mtime_ns for p in out.glob("table1/*/*/metrics.json")}
    res = run_experiment("table1", suite, out, jobs=1, progress=False)
    assert res["ran"] == 0 and res["done before"] == 6 and res["failed"] == 0
    assert {p: p.stat().st_mtime_ns for p in out.glob("table1/*/*/metrics.json")} == before


def test_parallel_matches_serial_and_isolates_failure(serial, parallel):
    out1 = serial[2]
    suite, out2, res = parallel
    assert res["ran"] == 7 and res["failed"] == 1
    for case in ("shepp", "blob"):
        for run in ("fdk", "sart"):
            a, b = _metrics(out1, case, run), _metrics(out2, case, run)
            # 1 vs 2 Dr.Jit threads per process: only the order of float32 sums may differ
            assert b["psnr_3d"] == pytest.approx(a["psnr_3d"], abs=1e-3)
            assert b["ssim_3d"] == pytest.approx(a["ssim_3d"], abs=1e-5)
    bad = out2 / "table1" / "blob" / "flaky"
    assert not (bad / "metrics.json").exists()
    assert "deliberate failure" in (bad / "error.txt").read_text()
    assert (out2 / "table1" / "shepp" / "flaky" / "metrics.json").is_file()
    runs = json.loads((out2 / "table1" / "runs.json").read_text())["runs"]
    status = {(r["case"], r["run"]): r["status"] for r in runs}
    assert status[("blob", "flaky")] == "failed" and status[("shepp", "flaky")] == "ran"


def test_killed_runner_leaves_index_of_finished_runs(tmp_path, monkeypatch):
    """runs.json is written as runs finish: a runner killed after the first run has
    recorded it (and nothing it did not finish)."""
    import drjit as dr
    import mi_grg.lab.runner as ex
    suite = _suite(tmp_path)

    def first_then_killed(func, tasks, jobs, desc, progress, on_result=None, client=None):
        threads = dr.thread_count()
        try:
            if on_result is None:              # simulating the data: all of it
                return [func(t) for t in tasks]
            on_result(0, func(tasks[0]))       # the first run, in this process
        finally:
            dr.set_thread_count(threads)
        raise KeyboardInterrupt                # then the runner is killed

    monkeypatch.setattr(ex, "_execute", first_then_killed)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_experiment("table1", suite, out, jobs=1, progress=False)
    runs = json.loads((out / "table1" / "runs.json").read_text())["runs"]
    assert len(runs) == 1 and runs[0]["status"] == "ran"
    assert (Path(runs[0]["dir"]) / "metrics.json").is_file()
    assert runs[0]["psnr_3d"] == pytest.approx(
        _metrics(out, runs[0]["case"], runs[0]["run"])["psnr_3d"])


def test_training_run_with_changed_defaults_is_run_again(tmp_path):
    """A finished gr run whose recorded config differs from what the current defaults give
    is not reused (dry run names the option), and is run again afresh."""
    suite = _tiny_gr_suite(tmp_path, iterations=2)
    out = tmp_path / "out"
    # gr, its paper-configuration row (gr-paper) and its classical step alone (pdhg-cold)
    assert run_experiment("table1", suite, out, jobs=1, progress=False)["ran"] == 3
    run_dir = out / "table1" / "shepp" / "gr"
    assert stale_options(run_dir) == []
    assert run_experiment("table1", suite, out, dry_run=True)["done before"] == 3
    m = json.loads((run_dir / "metrics.json").read_text())
    m["method_info"]["config"]["tv_every"] += 1       # as if run under another default
    (run_dir / "metrics.json").write_text(json.dumps(m))
    assert stale_options(run_dir) == ["tv_every"]
    # a field added later with its old behaviour as default: absent means that value ...
    del m["method_info"]["config"]["rebuild_keeps_field"]
    (run_dir / "metrics.json").write_text(json.dumps(m))
    assert stale_options(run_dir) == ["tv_every"]
    # configs recorded before "automatic" was None spelt it 0: still the same run
    m["method_info"]["config"].update(extent=0.0, graph_s=0.0, log_3d_every=0)
    (run_dir / "metrics.json").write_text(json.dumps(m))
    assert stale_options(run_dir) == ["tv_every"]
    # ... any other absent field is stale (the run cannot say what it used)
    del m["method_info"]["config"]["keep_state"]
    (run_dir / "metrics.json").write_text(json.dumps(m))
    assert stale_options(run_dir) == ["keep_state", "tv_every"]
    m["method_info"]["config"]["keep_state"] = "latest"
    (run_dir / "metrics.json").write_text(json.dumps(m))
    plan = run_experiment("table1", suite, out, dry_run=True)
    assert plan["todo"] == 1 and plan["runs"][0]["stale"] == ["tv_every"]
    md = write_report(out, tmp_path / "r.md").read_text()     # the report says so
    assert "- table1: 1 run(s), differing in tv_every" in md
    res = run_experiment("table1", suite, out, jobs=1, progress=False)
    assert res["ran"] == 1 and res["failed"] == 0
    assert stale_options(run_dir) == []
    assert "other defaults" not in write_report(out, tmp_path / "r.md").read_text()


def test_gr_paper_shares_gr_training(tmp_path, capsys):
    """gr-paper differs from gr only after training: it runs after gr, from gr's final
    checkpoint, and scores what gr's trained Gaussians alone score; planned again with gr
    finished, it takes gr's checkpoint at once. A twin trained under other options is not
    shared."""
    suite = _tiny_gr_suite(tmp_path, iterations=4)
    out = tmp_path / "out"
    case = out / "table1" / "shepp"
    plan = run_experiment("table1", suite, out, dry_run=True, methods="gr")
    row = {r["run"]: r for r in plan["runs"]}
    assert row["gr-paper"]["trains_with"] == str(case / "gr") and row["gr-paper"]["waits"]
    assert "trains_with" not in row["gr"]
    res = run_experiment("table1", suite, out, jobs=1, progress=False, methods="gr")
    assert res["failed"] == 0 and res["ran"] == 2
    gr, paper = (_metrics(out, "shepp", r) for r in ("gr", "gr-paper"))
    assert paper["method_info"]["init"].get("resumed_from")
    assert "resumed_from" not in gr["method_info"]["init"]
    assert paper["psnr_3d"] == pytest.approx(gr["method_info"]["result"]["parts"]["gaussians"],
                                             abs=1e-6)
    # its time is what it would take alone: gr's training wall clock and its own steps
    assert paper["seconds"] > paper["method_info"]["resumed_seconds"] > 0
    # gr finished, gr-paper to do again: the finished twin's checkpoint is taken at once
    shutil.rmtree(case / "gr-paper")
    row = {r["run"]: r for r in run_experiment("table1", suite, out, dry_run=True,
                                               methods="gr-paper")["runs"]}
    assert row["gr-paper"]["trains_with"] == str(case / "gr") and "waits" not in row["gr-paper"]
    assert run_experiment("table1", suite, out, jobs=1, progress=False,
                          methods="gr-paper")["ran"] == 1
    again = _metrics(out, "shepp", "gr-paper")
    assert again["method_info"]["init"].get("resumed_from")
    assert again["psnr_3d"] == pytest.approx(paper["psnr_3d"], abs=1e-6)
    # gr resuming for its result's steps (stale after training only) lends its checkpoint too
    shutil.rmtree(case / "gr-paper")
    m = _metrics(out, "shepp", "gr")
    m["method_info"]["config"]["fit_iterations"] += 1
    (case / "gr" / "metrics.json").write_text(json.dumps(m))
    row = {r["run"]: r for r in run_experiment("table1", suite, out, dry_run=True,
                                               methods="gr")["runs"]}
    assert row["gr"]["resumes"] and row["gr-paper"]["trains_with"] == str(case / "gr")
    assert row["gr-paper"]["waits"]
    # a finished gr trained under another option (its checkpoint says so) is no twin
    _rewrite_checkpoint_config(case / "gr" / "checkpoint.npz", tv_every=7)
    from mi_grg.lab.reuse import take_twin_checkpoint
    spec = next(s for s in plan_experiment("table1", load_suite(suite), methods={"gr-paper"}))
    (case / "gr-paper").mkdir()
    r = {"trains_with": str(case / "gr")}
    take_twin_checkpoint(spec, r, out)
    assert r["trains_with"] is None and not (case / "gr-paper" / "checkpoint.npz").exists()


def _rewrite_checkpoint_config(path: Path, **changes) -> None:
    """As if the checkpoint at ``path`` had been written under other training options."""
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    meta = json.loads(arrays["meta"].tobytes())
    meta["config"].update(changes)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(path, **arrays)


def test_a_run_resumes_only_where_its_trained_state_is_todays(tmp_path, capsys):
    """A finished gr run stale only in an option that acts after training (fit_iterations)
    resumes from its final checkpoint and redoes only the result's steps; one stale in a
    training option (tv_every) starts afresh. An interrupted run (a checkpoint, no
    metrics.json) resumes if its checkpoint was made under today's training config, and
    starts afresh (rather than failing) if not."""
    suite = _tiny_gr_suite(tmp_path, iterations=4)
    out, run_dir = tmp_path / "out", tmp_path / "out" / "table1" / "shepp" / "gr"
    run_experiment("table1", suite, out, jobs=1, progress=False, methods="gr")
    first = json.loads((run_dir / "metrics.json").read_text())
    assert "resumed_from" not in first["method_info"]["init"]
    assert (run_dir / "checkpoint.npz").is_file()
    # gr-paper, finished, would lend gr its checkpoint (test_gr_paper_shares_gr_training)
    twin = run_dir.parent / "gr-paper"
    shutil.rmtree(twin)

    def again(resumes):
        plan = run_experiment("table1", suite, out, dry_run=True, methods="gr")
        row = next(r for r in plan["runs"] if r["run"] == "gr")
        assert row["status"] == "todo" and row.get("resumes") is resumes
        from mi_grg.cli import main        # the dry run says so
        assert main(["experiment", "table1", "--suite", str(suite), "--out", str(out),
                     "--methods", "gr", "--dry-run"]) == 0
        line = next(x for x in capsys.readouterr().out.splitlines() if "shepp/gr " in x)
        assert ("resumes from its checkpoint" in line) is resumes, line
        res = run_experiment("table1", suite, out, jobs=1, progress=False, methods="gr")
        assert res["failed"] == 0 and stale_options(run_dir) == []
        shutil.rmtree(twin)
        return json.loads((run_dir / "metrics.json").read_text())

    def record(**changes):
        m = json.loads((run_dir / "metrics.json").read_text())
        m["method_info"]["config"].update(changes)
        (run_dir / "metrics.json").write_text(json.dumps(m))

    record(fit_iterations=first["method_info"]["config"]["fit_iterations"] + 1)
    assert stale_options(run_dir) == ["fit_iterations"]
    m = again(resumes=True)
    assert m["method_info"]["init"] == {"resumed_from": 4}
    assert m["method_info"]["resumed_seconds"] > 0
    assert m["psnr_3d"] == pytest.approx(first["psnr_3d"], abs=0.05)

    record(tv_every=first["method_info"]["config"]["tv_every"] + 1)
    assert "resumed_from" not in again(resumes=False)["method_info"]["init"]

    (run_dir / "metrics.json").unlink()                      # interrupted after its checkpoint
    assert again(resumes=True)["method_info"]["init"] == {"resumed_from": 4}

    (run_dir / "metrics.json").unlink()
    _rewrite_checkpoint_config(run_dir / "checkpoint.npz",
                               tv_every=first["method_info"]["config"]["tv_every"] + 1)
    assert "resumed_from" not in again(resumes=False)["method_info"]["init"]


def test_a_rule_change_marks_only_the_sizes_whose_count_it_changed():
    """A gr run that left ``iterations`` automatic is stale where the rule it recorded gives
    another count than today's at its size, not wherever the rule's name differs."""
    from mi_grg.lab.staleness import ITERATION_RULES, stale_keys
    from mi_grg.training.config import ITERATION_RULE, make_config
    from mi_grg.training.trainer import iteration_rule
    from mi_grg.data.simulate import default_geometry

    def run(n, rule):
        info = {"config": make_config("gr").to_flat(), "extent": 3.5}
        if rule is not None:
            info["iteration_rule"] = rule
        return {"method": "gr", "options": {}, "nVoxel": [n, n, n], "method_info": info}

    for n in (32, 64, 128, 256):
        now = iteration_rule(default_geometry(n=n, det=n, views=2))
        for name, rule in list(ITERATION_RULES.items()) + [(None, ITERATION_RULES["1500*n/64"])]:
            want = [] if rule(n) == now else ["iterations"]
            assert stale_keys(run(n, name)) == want, (n, name)
    assert stale_keys(run(64, "3000*sqrt(n/64)")) == []          # the same 3000
    assert stale_keys(run(128, "3000*sqrt(n/64)")) == ["iterations"]   # 4243, now 6000
    assert stale_keys(run(128, "a rule this code does not know")) == ["iterations"]
    no_size = run(64, "3000*sqrt(n/64)")          # no size recorded: the rule's name decides
    del no_size["nVoxel"]
    assert stale_keys(no_size) == ["iterations"]
    no_size["method_info"]["iteration_rule"] = ITERATION_RULE
    assert stale_keys(no_size) == []


def test_an_anchored_run_at_its_cap_is_stale_under_the_demand_rule():
    """A gr run whose refine_anchor="auto" took the anchor before densification's demand
    decided it (no verdict recorded) is stale where its count ended at the cap (today it
    refines plain), and only its result's steps are redone; runs below the cap, runs that
    went plain, runs with a verdict and runs that fixed the form are not stale."""
    from mi_grg.lab.staleness import stale_keys
    from mi_grg.training.config import AFTER_TRAINING, make_config

    def run(n, anchored=True, verdict=False, **options):
        anchor = {"rule": "auto", "anchored": anchored}
        if verdict:
            anchor["densification"] = {"growth": 0.0, "cap_share": n / 131072, "met": False}
        info = {"config": make_config("gr", **options).to_flat(), "extent": 3.5,
                "iteration_rule": "3000*sqrt(n/64) to 64, 3000*min(n/64,2) above",
                "n_gaussians": n, "max_gaussians": 131072, "refine": {"anchor": anchor}}
        return {"method": "gr", "options": options, "nVoxel": [64, 64, 64],
                "method_info": info}
    assert stale_keys(run(131070)) == ["refine_anchor"]
    assert "refine_anchor" in AFTER_TRAINING           # the trained state is kept
    assert stale_keys(run(118089)) == []                # below the cap: as before
    assert stale_keys(run(131070, anchored=False)) == []
    assert stale_keys(run(131070, verdict=True)) == []
    assert stale_keys(run(131070, refine_anchor="on")) == []


def test_fixed_sweep_classical_runs_are_stale_under_the_heldout_default():
    from mi_grg.lab.staleness import stale_keys
    assert stale_keys({"method": "asd-pocs", "options": {}}) == ["stop"]   # ran before
    assert stale_keys({"method": "asd-pocs", "options": {},
                       "method_info": {"protocol": "heldout"}}) == []
    assert stale_keys({"method": "sart", "options": {"stop": "none", "n_iter": 10}}) == []
    assert stale_keys({"method": "sart-curve", "options": {}}) == []
    assert stale_keys({"method": "fdk", "options": {}}) == []


def _table_row(md: str, section: str, name: str) -> list:
    part = md.split(section, 1)[1]
    for line in part.splitlines():
        if line.startswith(f"| {name} |"):
            return [c.strip() for c in line.strip().strip("|").split("|")]
    raise AssertionError(f"no row {name!r} after {section!r}")


def test_report_numbers_come_from_metrics(parallel, tmp_path):
    suite, out, _ = parallel
    path = write_report(out, tmp_path / "docs" / "results.md")
    md = path.read_text()
    # independent read-back: category means from metrics.json
    m = {(c, r): _metrics(out, c, r) for c in ("shepp", "blob") for r in ("fdk", "sart")}
    for run, name in (("fdk", "FDK"), ("sart", "SART")):
        row = _table_row(md, "## Table 1", name)
        ho, ao = m[("shepp", run)], m[("blob", run)]
        assert row[1] == f"{ho['psnr_3d']:.2f}" and row[2] == f"{ho['ssim_3d']:.3f}"
        assert row[3] == f"{ao['psnr_3d']:.2f}" and row[4] == f"{ao['ssim_3d']:.3f}"
        assert row[5] == f"{(ho['psnr_3d'] + ao['psnr_3d']) / 2:.2f}"
        assert row[6] == f"{(ho['ssim_3d'] + ao['ssim_3d']) / 2:.3f}"
    # the failed run: its category and the overall mean are missing, never invented
    flaky = _table_row(md, "## Table 1", "flaky")
    assert flaky[1] == f"{_metrics(out, 'shepp', 'flaky')['psnr_3d']:.2f}"
    assert flaky[3] == "—" and flaky[5] == "—"
    # methods that did not run are rows of dashes
    assert set(_table_row(md, "## Table 1", "GR-Gaussian (gr)")[1:]) == {"—"}
    # the paper's numbers are there and labelled as the paper's
    paper = _table_row(md, "The paper's Table 1", "Ours (GR-Gaussian)")
    assert paper[1:3] == ["33.47", "0.891"] and paper[9:11] == ["35.95", "0.858"]
    assert "X-3D" in md and "NOT comparable" in md
    assert PAPER_TABLE1["SART"][3] == (31.14, 0.825)
    # montages and the regenerating command
    assert re.search(r"!\[best \w+\]\(img/results/montage_best_\w+\.png\)", md)
    assert any((tmp_path / "docs" / "img" / "results").glob("montage_*.png"))
    assert f"mi-grg experiment table1 --suite {suite} --out {out}" in md
    # a second report in the same folder keeps its figures apart: the first's stay as written
    first = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
             for p in (tmp_path / "docs" / "img" / "results").glob("*.png")}
    other = write_report(out, tmp_path / "docs" / "other.md").read_text()
    assert re.search(r"!\[best \w+\]\(img/other/montage_best_\w+\.png\)", other)
    assert any((tmp_path / "docs" / "img" / "other").glob("montage_*.png"))
    assert {p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
            for p in (tmp_path / "docs" / "img" / "results").glob("*.png")} == first
    # which code produced the runs, as each metrics.json recorded it
    assert f"mi_grg {_metrics(out, 'shepp', 'fdk')['machine']['mi_grg']}" in md


def _fake_run(out: Path, exp: str, case: str, run: str, cat: str, method: str, **metrics):
    d = out / exp / case / run
    d.mkdir(parents=True, exist_ok=True)
    (d / "metrics.json").write_text(json.dumps({"method": method, "seconds": 1.0, **metrics}))
    runs_file = out / exp / "runs.json"
    runs = json.loads(runs_file.read_text()) if runs_file.exists() else {"runs": []}
    runs["runs"].append({"case": case, "run": run, "category": cat, "label": run,
                         "method": method, "views": 25})
    runs_file.write_text(json.dumps(runs))
    return d


def test_summary_lines(tmp_path):
    out = tmp_path / "res"
    vals = {"a": {"fdk": 20.0, "r2": 30.0, "gr": 31.0}, "b": {"fdk": 21.0, "r2": 33.0,
                                                             "gr": 32.5}}
    for case, per in vals.items():
        for method, p in per.items():
            _fake_run(out, "table1", case, method, "HO", method, psnr_3d=p, ssim_3d=0.9,
                      seconds={"fdk": 1.0, "r2": 100.0, "gr": 150.0}[method])
    lines = summary_lines(out)
    assert len(lines) == 4 and "No held-out-stopped classical runs" in lines[3]
    assert "best 3-D PSNR on 1 of 2 cases" in lines[0] and "a +1.00 dB" in lines[0]
    assert "+0.25 dB on average" in lines[0]           # mean of +1.0 and -0.5
    assert "b (R2-Gaussian (r2) ahead by 0.50 dB)" in lines[1]
    assert "gr / r2 = 1.50x" in lines[2] and "complete" not in lines[2]
    assert "training" not in lines[2]                  # no run says how long its result took
    for case, steps in (("a", 40.0), ("b", 60.0)):     # gr's time: training + result's steps
        m = _metrics(out, case, "gr")
        m["method_info"] = {"result": {"seconds": steps}}
        (out / "table1" / case / "gr" / "metrics.json").write_text(json.dumps(m))
    assert "of gr's 150.0 s, training 100.0 s and the result's steps 50.0 s" in \
        summary_lines(out)[2], summary_lines(out)[2]
    # a case without r2 / gr: times and the extra table are over the complete cases only
    _fake_run(out, "table1", "c", "fdk", "AO", "fdk", psnr_3d=25.0, ssim_3d=0.5, seconds=9.0)
    lines = summary_lines(out)
    assert "over the 2 complete cases" in lines[2] and "gr / r2 = 1.50x" in lines[2]
    assert "FDK 1.00 s" in lines[2], lines[2]          # case c (9 s) left out
    md = write_report(out, tmp_path / "r.md").read_text()
    assert "Only 2 of the 3 cases have a result from every method" in md
    over = md[md.index("Only 2 of the 3"):]
    row = _table_row(over, "Only 2 of the 3", "GR-Gaussian (gr)")
    assert row[1:3] == ["31.75", "0.900"]              # mean of 31.0 and 32.5 over a, b
    # a case with Gaussian rows only is no win over every method: it is left out and named
    for method, p in (("gr-paper", 28.0), ("gr", 40.0)):
        _fake_run(out, "table1", "d", method, "AO", method, psnr_3d=p, ssim_3d=0.9)
    lines = summary_lines(out)
    assert "best 3-D PSNR on 1 of 2 cases" in lines[0] and "d +" not in lines[0], lines[0]
    assert "left out, no classical row among these runs: d" in lines[0]
    assert "d (" not in lines[1]


def test_fair_margin_oracle_and_anytime_tables(tmp_path):
    """gr's margin is taken against the held-out-stopped classical rows (and, separately,
    the fixed ones); the oracle is shown beside them; the any-time table takes the best
    point within each budget."""
    from mi_grg.lab.report import DASH, anytime_table, classical_margin, oracle_rows
    from mi_grg.lab.report_tables import cold_peak_margin
    out = tmp_path / "res"
    held = {"protocol": "heldout", "chosen": {"setting": {"alpha": 0.02}, "sweeps": 7},
            "oracle": {"psnr_3d_best": 29.5, "best_sweep": 5, "gap_db": 0.5},
            "oracle_seconds": 40.0}
    for case, (asd, fixed, gr) in {"a": (29.0, 27.0, 31.0), "b": (30.0, 26.0, 30.5)}.items():
        _fake_run(out, "table1", case, "fdk", "HO", "fdk", psnr_3d=20.0, ssim_3d=0.5)
        _fake_run(out, "table1", case, "asd-pocs", "HO", "asd-pocs", psnr_3d=asd,
                  ssim_3d=0.8, seconds=10.0, method_info=held)
        _fake_run(out, "table1", case, "asd-pocs-fixed", "HO", "asd-pocs", psnr_3d=fixed,
                  ssim_3d=0.8, seconds=5.0)
        _fake_run(out, "table1", case, "gr", "HO", "gr", psnr_3d=gr, ssim_3d=0.9,
                  seconds=100.0)
    rows = load_runs(out)["table1"]
    mg = classical_margin(rows)
    assert [(c, m, round(d, 6)) for c, m, d in mg["heldout"]] == [("a", "asd-pocs", 2.0),
                                                                  ("b", "asd-pocs", 0.5)]
    assert [round(d, 6) for _, _, d in mg["fixed"]] == [4.0, 4.5]
    line = summary_lines(out)[3]
    assert "+1.25 dB on average over 2 case(s)" in line and "+4.25 dB" in line
    # PDHG under Morozov's rule is a fair row too: where it is best, the margin is to it
    _fake_run(out, "table1", "b", "pdhg-morozov", "HO", "pdhg", psnr_3d=30.25, ssim_3d=0.8,
              seconds=10.0, method_info=held)
    mg = classical_margin(load_runs(out)["table1"])
    assert [(c, m, round(d, 6)) for c, m, d in mg["heldout"]] == [("a", "asd-pocs", 2.0),
                                                                  ("b", "pdhg-morozov", 0.25)]
    assert "PDHG (Morozov) 10.0 s" in summary_lines(out)[2]   # not "PDHG" twice
    h, b = oracle_rows(rows)
    assert b[0] == ["a", "asd-pocs", "29.00", "alpha=0.02, 7 sweeps", "29.50 (5)", "0.50"]
    h, b = anytime_table(rows)
    assert h[2:] == ["best within 1 s", "best within 10 s", "best within 60 s",
                     "best within 300 s"]
    by = {(r[0], r[1]): r[2:] for r in b}
    assert by[("a", "asd-pocs")] == [DASH, "29.00", "29.00", "29.00"]
    assert by[("a", "asd-pocs-fixed")] == [DASH, "27.00", "27.00", "27.00"]
    assert by[("a", "gr")] == [DASH, DASH, DASH, "31.00"]
    # cold PDHG's logged curve: its best iteration (an oracle bound) beside its result
    cold = {"protocol": "fixed", "iterations": 300, "lam": 0.003,
            "oracle": {"psnr_3d_best": 30.75, "best_sweep": 120, "gap_db": 0.5}}
    _fake_run(out, "table1", "a", "pdhg-cold", "HO", "pdhg", psnr_3d=30.25, ssim_3d=0.8,
              seconds=20.0, method_info=cold)
    rows = load_runs(out)["table1"]
    assert [(c, round(d, 6), k) for c, d, k in cold_peak_margin(rows)] == [("a", 0.25, 120)]
    assert ["a", "pdhg-cold", "30.25", "lam=0.003, 300 iterations (fixed)", "30.75 (120)",
            "0.50"] in oracle_rows(rows)[1]
    assert "at its best iteration" in summary_lines(out)[3] and "a +0.25 at 120" in \
        summary_lines(out)[3]
    _fake_run(out, "speed", "a", "fdk", "HO", "fdk", psnr_3d=20.0, ssim_3d=0.5)
    md = write_report(out, tmp_path / "r.md").read_text()
    assert "oracle" in md and "29.50 (5)" in md
    # the speed plot of case a shows Table 1's held-out run beside the speed runs
    assert "asd-pocs (held-out): point" in md and "| a | asd-pocs (held-out) |" in md
    assert (tmp_path / "img" / "r" / "speed_a.png").is_file()


def test_iteration_plot_and_replayed_stop(tmp_path):
    # the early-stop rule replayed on a log: stop at the first value 0.5 % below the best
    # (noise 0: the fraction alone; the scatter margin: test_early_stop.py)
    its, vals = [10, 20, 30, 40, 50], [10.0, 12.0, 13.0, 12.94, 12.9]
    assert replay(its, vals, patience=1, noise=0) == (50, 30)   # 12.94 > 12.935
    # patience 2 needs two such values in a row; a dip that recovers is not one
    its2, vals2 = [10, 20, 30, 40, 50, 60, 70], [10.0, 13.0, 12.9, 12.95, 12.9, 12.8, 12.7]
    assert replay(its2, vals2, patience=2, noise=0) == (60, 20)
    assert replay(its2, vals2, patience=1, noise=0) == (30, 20)
    # evaluations before ``start`` (densification) are not judged
    assert replay(its2, vals2, start=40, patience=2, noise=0) == (70, 40)
    # the default margin is wider than 0.5 % where the values scatter more than that
    wobbly = [20.0, 21.0, 20.6, 21.4, 21.0, 21.8, 21.3, 21.1, 21.0, 22.0]
    w_its = list(range(10, 110, 10))
    assert replay(w_its, wobbly, patience=2, noise=0) == (80, 60)
    assert replay(w_its, wobbly) == (None, 100)
    falls = [10.0, 13.0, 12.9, 12.95, 12.9, 12.0, 11.9]      # a drop well beyond the scatter
    out = tmp_path / "res"
    d = _fake_run(out, "iterations", "c1", "gr-nostop", "HO", "gr", psnr_3d=20.0,
                  method_info={"iterations_run": 50, "iterations_planned": 50,
                               "stopped_by": "iteration budget (50) reached"})
    (d / "train_log.csv").write_text(
        "iteration,seconds,loss,heldout_psnr,psnr_3d,n_gaussians\n" + "".join(
            f"{i},{i / 10},0.1,{v},{v + 5},100\n" for i, v in zip(its2, falls)))
    md = write_report(out, tmp_path / "r.md").read_text()
    # the report replays the default rule (patience 2, margin >= 3 x the scatter)
    assert replay(its2, falls) == (60, 20)
    assert "replayed_stop: 60" in md and "best_heldout_iteration: 20" in md
    assert (tmp_path / "img" / "r" / "iterations_c1.png").stat().st_size > 1000
    assert len(load_runs(out)["iterations"]) == 1


def test_longest_runs_are_started_first(tmp_path):
    """Trained runs before the baselines, the fuller volume's first, no-stop runs first
    among equals; the order comes from the data sets on disk."""
    suite = load_suite(_suite(tmp_path, methods=("fdk", "sart", "r2", "gr")))
    out = tmp_path / "out"
    specs = plan_experiment("table1", suite)
    for name, fill in (("shepp", 0.25), ("blob", 0.75)):
        d = out / "data" / name
        d.mkdir(parents=True)
        v = np.zeros(64, np.float32)
        v[:int(fill * 64)] = 1.0
        np.save(d / "vol_gt.npy", v.reshape(4, 4, 4))
    cost = {(s.case.name, s.method): expected_cost(s, out) for s in specs}
    assert cost[("blob", "gr")] == pytest.approx(1.75) and cost[("shepp", "r2")] == 1.25
    assert cost[("blob", "sart")] > cost[("blob", "fdk")] == 0.0
    order = [(s.case.name, s.run) for s in sorted(specs, key=lambda s: -expected_cost(s, out))]
    assert order[:6] == [("blob", "r2"), ("blob", "gr"), ("blob", "gr-paper"),
                         ("shepp", "r2"), ("shepp", "gr"), ("shepp", "gr-paper")]
    assert {m for _, m in order[-2:]} == {"fdk"}
    nostop = [s for s in plan_experiment("iterations", suite) if s.run.endswith("nostop")]
    assert nostop and expected_cost(nostop[0], out) > cost[(nostop[0].case.name, "gr")]


def test_methods_filter_takes_row_names(tmp_path):
    """--methods keeps a row by its own name (gr-paper without gr, pdhg-cold without the
    PDHG rules); a name that is neither a method nor a row is an error that lists both."""
    suite = load_suite(_suite(tmp_path, methods=("fdk", "pdhg", "gr")))
    only = plan_experiment("table1", suite, methods={"gr-paper"}, cases=["shepp"])
    assert [(s.run, s.method) for s in only] == [("gr-paper", "gr")]
    assert only[0].options["refine"] == "none"
    cold = {s.run for s in plan_experiment("table1", suite, methods={"pdhg-cold", "fdk"})}
    assert cold == {"pdhg-cold", "fdk"}
    with pytest.raises(ValueError, match=r"gr-papr.*their rows: .*gr-paper.*pdhg-cold"):
        run_experiment("table1", tmp_path / "suite.json", tmp_path / "out", dry_run=True,
                       methods="fdk,gr-papr")


def test_repo_suites_are_valid():
    for kind, n, det in (("cpu", 64, 96), ("cpu_full", 64, 96), ("cpu_128", 128, 192),
                         ("gpu", 256, 512)):
        suite = load_suite(REPO / "experiments" / f"suite_{kind}.json")
        assert len(suite.cases) >= 8
        assert {c.category for c in suite.cases} == {"HO", "BS", "AO"}
        for c in suite.cases:
            assert (c.views, c.n, c.det) == (25, n, det)
            assert c.noise == {"I0": 1e4, "electronic_std": 10.0}
        for name in EXPERIMENTS:
            assert plan_experiment(name, suite), name
    res = run_experiment("all", REPO / "experiments" / "suite_cpu.json", "/nonexistent/x",
                         dry_run=True)
    t1 = [r for r in res["runs"] if r["experiment"] == "table1"]
    # fdk, sart, sart-fixed, asd-pocs, asd-pocs-best, asd-pocs-fixed, pdhg, pdhg-best,
    # pdhg-morozov, pdhg-cold, r2, gr, gr-paper
    assert len(t1) == 13 * len(load_suite(REPO / "experiments" / "suite_cpu.json").cases)
    assert {r["run"] for r in t1 if r["run"].startswith("pdhg")} == {
        "pdhg", "pdhg-best", "pdhg-morozov", "pdhg-cold"}
    cold = next(r for r in t1 if r["run"] == "pdhg-cold")
    from mi_grg.training.config import make_config
    proto = make_config("gr").protocol
    assert cold["options"]["lam"] == proto.refine_lam and cold["options"]["stop"] == "none"
    assert cold["options"]["n_iter"] >= 5 * proto.refine_max_iterations
    assert res["todo"] + res["duplicate"] == res["planned"]   # shared runs are not rerun
    assert not Path("/nonexistent/x").exists()


def test_all_runs_the_experiments_the_suite_lists(tmp_path):
    suite = _suite(tmp_path)                      # lists table1 only
    res = run_experiment("all", suite, tmp_path / "out", dry_run=True)
    assert {r["experiment"] for r in res["runs"]} == {"table1"}
    raw = json.loads(suite.read_text())
    del raw["experiments"]                        # lists none: every experiment
    suite.write_text(json.dumps(raw))
    res = run_experiment("all", suite, tmp_path / "out", dry_run=True)
    assert {r["experiment"] for r in res["runs"]} == set(EXPERIMENTS)


def test_suite_validation(tmp_path):
    bad = {"cases": [{"name": "a", "category": "XX", "source": "shepp", "views": 5,
                      "test_views": 2, "n": 8, "det": 8, "mode": "cone", "noise": None,
                      "seed": 0}]}
    p = tmp_path / "s.json"
    p.write_text(json.dumps(bad))
    with pytest.raises(SuiteError, match="category"):
        load_suite(p)
    del bad["cases"][0]["seed"]
    bad["cases"][0]["category"] = "HO"
    p.write_text(json.dumps(bad))
    with pytest.raises(SuiteError, match="seed"):
        load_suite(p)


def test_seeds_plan_shares_seed_0_with_table1(tmp_path):
    raw = json.loads(_suite(tmp_path).read_text())
    raw["experiments"] = {"table1": {"methods": ["r2", "gr"]},
                          "seeds": {"seeds": [0, 4], "cases": ["shepp"]}}
    path = tmp_path / "seeds.json"
    path.write_text(json.dumps(raw))
    suite = load_suite(path)
    runs = {s.run: s for s in plan_experiment("seeds", suite)}
    assert sorted(runs) == ["gr_s0", "gr_s4", "r2_s0", "r2_s4"]
    assert runs["gr_s4"].options == {"seed": 4} and runs["gr_s0"].options == {}
    t1 = {s.run: s for s in plan_experiment("table1", suite) if s.case.name == "shepp"}
    assert runs["gr_s0"].key() == t1["gr"].key() != runs["gr_s4"].key()
    res = run_experiment("all", path, tmp_path / "out", dry_run=True)
    # table1 (r2, gr, gr-paper and gr's cold PDHG part on 2 cases) + the two s4 runs
    assert res["duplicate"] == 2 and res["todo"] == 4 * 2 + 2


def test_unknown_experiment_key_is_an_error(tmp_path):
    raw = json.loads(_suite(tmp_path).read_text())
    raw["experiments"] = {"seeds": {"seed": [1, 2]}}
    path = tmp_path / "typo.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(SuiteError, match=r"experiments.seeds has unknown key\(s\) \['seed'\]"):
        load_suite(path)


def test_seeds_table_pairs_runs_by_seed(tmp_path):
    out = tmp_path / "res"
    vals = {"a": {0: (30.0, 30.3), 1: (30.2, 30.1), 2: (29.9, 30.4)},
            "b": {0: (25.0, 25.5), 1: (25.1, None)}}          # seed 1 of b: gr missing
    for case, per in vals.items():
        for sd, (r2, gr) in per.items():
            # SSIM = PSNR / 100 - 0.2, so its paired differences are the PSNR ones / 100
            _fake_run(out, "seeds", case, f"r2_s{sd}", "HO", "r2", psnr_3d=r2,
                      ssim_3d=r2 / 100 - 0.2)
            if gr is not None:
                _fake_run(out, "seeds", case, f"gr_s{sd}", "HO", "gr", psnr_3d=gr,
                          ssim_3d=gr / 100 - 0.2)
    rows_in = load_runs(out)["seeds"]
    h, body, pooled = seeds_table(rows_in)
    rows = {r[0]: dict(zip(h, r)) for r in body}
    d = np.array([0.3, -0.1, 0.5, 0.5])
    assert rows["a"]["gr − r2 (paired)"] == f"{np.mean(d[:3]):+.2f} ± {np.std(d[:3], ddof=1):.2f}"
    assert rows["a"]["gr ahead"] == "2 of 3" and rows["a"]["range of gr − r2"] == "-0.10 .. +0.50"
    assert rows["b"]["r2 PSNR"].startswith("25.05 ± ") and rows["b"]["gr PSNR"] == "25.50"
    assert pooled["n"] == 4 and abs(pooled["mean"] - d.mean()) < 1e-12
    assert abs(pooled["se"] - np.std(d, ddof=1) / 2) < 1e-12

    hs, body_s, pooled_s = seeds_table(rows_in, "ssim_3d")
    rows_s = {r[0]: dict(zip(hs, r)) for r in body_s}
    assert "gr SSIM" in hs and rows_s["b"]["gr SSIM"] == f"{0.255 - 0.2:.4f}"
    assert rows_s["a"]["range of gr − r2"] == "-0.0010 .. +0.0050"
    assert abs(pooled_s["mean"] - d.mean() / 100) < 1e-9
    assert abs(pooled_s["se"] - np.std(d / 100, ddof=1) / 2) < 1e-9
    with pytest.raises(ValueError, match="key must be one of"):
        seeds_table(rows_in, "psnr")

    md = write_report(out, tmp_path / "r.md").read_text()
    assert "## Training seeds" in md and md.count("all (4 pairs)") == 2
    verdict = "exceeds" if d.mean() > 2 * np.std(d, ddof=1) / 2 else "does not exceed"
    assert f"the mean {verdict} twice its standard error" in md
    assert f"gr − r2 = {d.mean() / 100:+.4f} SSIM" in md


def test_table2_rows_each_add_one_component_to_r2(tmp_path):
    """Properties of Table 2's rows (not a copy of them): the first is plain r2, the last
    plain gr; every row between is r2 with options that move only fields where r2 and gr
    differ, each to gr's value; no two rows are the same; together they switch on every
    field in which gr differs from r2. The plan runs the rows in this order, with the
    suite's options under each row's own."""
    from mi_grg.lab.plan import table2_variants
    rows = table2_variants()
    r2, gr = make_config("r2").to_flat(), make_config("gr").to_flat()
    differ = {k for k in gr if gr[k] != r2[k]}
    assert differ
    assert rows[0][1:3] == ("r2", {}) and rows[-1][1:3] == ("gr", {})
    changed_sets = []
    for run, method, options, label in rows[1:-1]:
        assert method == "r2", run
        cfg = make_config("r2", **options).to_flat()
        changed = {k for k in cfg if cfg[k] != r2[k]}
        assert changed and changed <= differ, (run, changed - differ)
        assert all(cfg[k] == gr[k] for k in changed), run
        changed_sets.append(frozenset(changed))
    assert len(set(changed_sets)) == len(changed_sets)
    assert set().union(*changed_sets) == differ
    assert len({r[0] for r in rows}) == len({r[3] for r in rows}) == len(rows)

    raw = json.loads(_suite(tmp_path).read_text())
    raw["experiments"] = {"table2": {"cases": ["shepp"]}}
    path = tmp_path / "t2.json"
    path.write_text(json.dumps(raw))
    runs = {s.run: s for s in plan_experiment("table2", load_suite(path))}
    assert list(runs) == [r[0] for r in rows]
    base = runs["r2"].options
    for run, method, options, _ in rows[1:-1]:
        assert runs[run].method == method and runs[run].options == {**base, **options}, run


def test_the_checkpoint_interval_never_makes_a_run_stale():
    """checkpoint_every decides only when checkpoints are written: a run recorded with
    another interval (500, the fixed default before it became automatic) is not stale,
    while another value of a field that changes the result is."""
    from mi_grg.lab.staleness import stale_keys
    from mi_grg.training.config import make_config

    def run(**recorded):
        info = {"config": {**make_config("gr").to_flat(), **recorded}, "extent": 3.5,
                "iteration_rule": "3000*sqrt(n/64) to 64, 3000*min(n/64,2) above"}
        return {"method": "gr", "options": {}, "nVoxel": [64, 64, 64], "method_info": info}
    assert stale_keys(run()) == []
    assert stale_keys(run(checkpoint_every=500)) == []
    assert stale_keys(run(checkpoint_every=500, k=5)) == ["k"]


def test_a_hybrids_parts_are_rows_and_the_cold_classical_step_competes(tmp_path):
    """gr's trained Gaussians alone (from its record of the result's parts) get a row of
    their own that never competes with gr; the cold PDHG at gr's weight competes in both
    margins (held-out and fixed)."""
    from mi_grg.lab.report import classical_margin, summary_lines
    from mi_grg.lab.report_tables import table1_rows
    out = tmp_path / "res"
    held = {"protocol": "heldout", "chosen": {"setting": {"lam": 0.003}, "sweeps": 60}}
    parts = {"result": {"parts": {"gaussians": 29.5, "voxel_averaged": 30.0, "export": 31.0}}}
    for case, (pdhg, cold, gr) in {"a": (30.0, 30.5, 31.0), "b": (30.0, 29.0, 32.0)}.items():
        _fake_run(out, "table1", case, "fdk", "HO", "fdk", psnr_3d=20.0, ssim_3d=0.5)
        _fake_run(out, "table1", case, "pdhg", "HO", "pdhg", psnr_3d=pdhg, ssim_3d=0.8,
                  method_info=held)
        _fake_run(out, "table1", case, "pdhg-cold", "HO", "pdhg", psnr_3d=cold, ssim_3d=0.8)
        _fake_run(out, "table1", case, "gr", "HO", "gr", psnr_3d=gr, ssim_3d=0.9,
                  method_info=parts)
    rows = load_runs(out)["table1"]
    part = [r for r in rows if r["run"] == "gr-gaussians"]
    assert [(r["case"], r["metrics"]) for r in part] == [("a", {"psnr_3d": 29.5}),
                                                         ("b", {"psnr_3d": 29.5})]
    mg = classical_margin(rows)
    assert [(c, m, round(d, 6)) for c, m, d in mg["heldout"]] == [("a", "pdhg-cold", 0.5),
                                                                  ("b", "pdhg", 2.0)]
    h, b = table1_rows(rows)
    by = {line[0]: line for line in b}
    assert by["gr's trained Gaussians alone (before its result's steps)"][3] == "29.50"
    # the Gaussians alone are gr's part, not a competitor: gr is best on both cases
    assert "best 3-D PSNR on 2 of 2 cases" in summary_lines(out)[0]


def test_table1_has_a_row_for_every_weight_rule_of_each_classical_method():
    """Every rule a classical method has, besides its default (the plain row), is a row of
    Table 1 and a name in the report; the rows' options are the method's rule options."""
    from mi_grg.classical.iterative import ALPHA_RULES
    from mi_grg.classical.pdhg import DEFAULT_LAM_RULE
    from mi_grg.lab.report_tables import CLASSICAL, METHOD_NAMES
    from mi_grg.lab.suite import RULE_ROWS
    from mi_grg.protocol.search import RULES
    pdhg = {o["lam_rule"] for _, o, _ in RULE_ROWS["pdhg"]}
    assert pdhg == set(RULES) - {DEFAULT_LAM_RULE}
    asd = {o["alpha_rule"] for _, o, _ in RULE_ROWS["asd-pocs"]}
    assert asd == set(ALPHA_RULES) - {ALPHA_RULES[0]}
    for rows in RULE_ROWS.values():
        for run, _, _ in rows:
            assert run in CLASSICAL and run in METHOD_NAMES


def test_the_record_keeps_runs_whose_folder_is_gone(serial, tmp_path):
    """A report with --record copies OUT's finished runs into the record (metrics.json
    without its volume files) and counts the record's other runs: a later OUT that lacks
    them still reports them, with the numbers they were recorded with."""
    from mi_grg.lab.report_tables import table1_rows
    _, _, out, _ = serial
    record = tmp_path / "docs" / "runs"
    write_report(out, tmp_path / "docs" / "first.md", record=record)
    for case in ("shepp", "blob"):
        for run in ("fdk", "sart"):
            kept = json.loads((record / "table1" / case / run / "metrics.json").read_text())
            mine = _metrics(out, case, run)
            assert kept["record_of"] == str(out / "table1" / case / run)
            assert "volume_files" not in kept and "volume_files" in mine
            assert {k: v for k, v in kept.items() if k != "record_of"} == \
                {k: v for k, v in mine.items() if k != "volume_files"}
    index = json.loads((record / "table1" / "runs.json").read_text())
    assert sorted((r["case"], r["run"]) for r in index["runs"]) == sorted(
        (r["case"], r["run"]) for r in load_runs(out)["table1"] if r["metrics"])
    assert any(c.startswith("mi-grg experiment table1") for c in index["commands"])
    # the same report again rewrites nothing in the record
    for f in record.rglob("*.json"):
        os.utime(f, ns=(1, 1))
    write_report(out, tmp_path / "docs" / "first.md", record=record)
    assert {f.stat().st_mtime_ns for f in record.rglob("*.json")} == {1}
    # a later results folder: one new case, shepp's fdk run again, blob's fdk broken
    later = tmp_path / "later"
    _fake_run(later, "table1", "c", "fdk", "HO", "fdk", psnr_3d=25.0, ssim_3d=0.5)
    _fake_run(later, "table1", "shepp", "fdk", "HO", "fdk", psnr_3d=99.0, ssim_3d=0.99)
    (_fake_run(later, "table1", "blob", "fdk", "AO", "fdk") / "metrics.json").write_text("{")
    md = write_report(later, tmp_path / "docs" / "later.md", record=record).read_text()
    rows = load_runs(record)["table1"]                 # the record alone is a results folder
    got = {(r["case"], r["run"]): r["metrics"]["psnr_3d"] for r in rows}
    assert got[("shepp", "fdk")] == 99.0 and got[("c", "fdk")] == 25.0
    assert got[("blob", "fdk")] == _metrics(out, "blob", "fdk")["psnr_3d"]   # not removed
    assert got[("shepp", "sart")] == _metrics(out, "shepp", "sart")["psnr_3d"]
    h, b = table1_rows(rows)
    fdk = next(line for line in b if line[0] == "FDK")
    assert fdk[1] == f"{(99.0 + 25.0) / 2:.2f}"       # HO: shepp run again, and c
    assert fdk[3] == f"{_metrics(out, 'blob', 'fdk')['psnr_3d']:.2f}"   # AO: blob, recorded
    assert _table_row(md, "## Table 1", "FDK")[1:] == fdk[1:]
    assert "From the record" in md and "table1/blob" in md and "table1/c," not in md
    assert f"--record {record}" in md and "mi-grg experiment table1" in md
    # the record alone, where the results folder is gone
    alone = write_report(tmp_path / "gone", tmp_path / "docs" / "alone.md",
                         record=record).read_text()
    assert _table_row(alone, "## Table 1", "FDK") == _table_row(md, "## Table 1", "FDK")
    # a report over the record alone keeps the figures the report before made of its cases
    img = tmp_path / "docs" / "img" / "first"
    before = {p.name: p.read_bytes() for p in img.glob("*.png")}
    assert "compare_shepp.png" in before and "compare_blob.png" in before
    again = write_report(tmp_path / "gone", tmp_path / "docs" / "first.md",
                         record=record).read_text()
    assert {p.name: p.read_bytes() for p in img.glob("compare_*.png")} == {
        k: v for k, v in before.items() if k.startswith("compare_")}
    assert "![shepp](img/first/compare_shepp.png)" in again
    assert "The figures of blob, shepp are those of the report" in again
