"""The decision protocol (mi_grg.protocol): the weight search, the discrepancy principle,
the split's bad input, the package layering, and that no decision reads the ground truth
or the test views.

References: scripted methods whose held-out error has a known best weight; hand-computed
residual sequences; the import graph parsed from the source; and for the leakage test
the same runs with the ground truth and test views replaced by noise (on one thread,
where every method is bit-reproducible).
"""
import ast
import math
from pathlib import Path

import numpy as np
import pytest

import mi_grg  # noqa: F401  (before mitsuba)

from mi_grg.core.geometry import circular_angles
from mi_grg.core.joseph import forward_project
from mi_grg.data.case import Case
from mi_grg.protocol.discrepancy import discrepancy_stop, noise_level
from mi_grg.protocol.heldout import run_heldout
from mi_grg.protocol.search import LogGrid
from mi_grg.protocol.split import decision_split

ROOT = Path(__file__).resolve().parents[1]


def small_case(views=9):
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(16, 16),
                          sDetector=(3.0, 3.0), nVoxel=(12, 12, 12), sVoxel=(2.0, 2.0, 2.0),
                          angles=circular_angles(views))
    x = np.zeros(geo.nVoxel, np.float32)
    x[3:9, 4:8, 3:9] = 1.0
    return Case(geometry=geo, train=forward_project(x, geo), vol_gt=None), x


def weighted_method(x_true, best_weight):
    """A scripted method: its volume misses x_true by |log10(w / best_weight)| x a ramp, so
    the held-out PSNR is highest at ``best_weight``, lower the further w lies from it."""
    ramp = np.linspace(0, 1, 12, dtype=np.float32)[:, None, None] * np.ones((12,) * 3,
                                                                             np.float32)
    tried = []

    def run(proj, geo, n_iter, callback, progress, lam):
        tried.append(lam)
        vol = x_true + 0.1 * abs(math.log10(lam / best_weight)) * ramp + 0.01 * ramp
        for it in range(n_iter):
            if callback(it, vol):
                break
        return vol
    return run, tried


@pytest.mark.parametrize("best, widened", [(3e-5, "below"), (0.4, "above"), (0.003, None)])
def test_weight_search_widens_until_its_choice_is_interior(best, widened):
    case, x = small_case()
    run, tried = weighted_method(x, best)
    grid = LogGrid("lam", [0.001, 0.003, 0.01], max_extend=4)
    _, info = run_heldout(case, run, grid, project=forward_project, max_sweeps=4, name="t",
                          progress=False)
    s = info["search"]
    chosen = info["chosen"]["setting"]["lam"]
    assert s["interior"] and s["chosen"] == chosen
    assert abs(math.log10(chosen / best)) <= 0.25        # the grid value nearest the best
    assert sorted(set(tried[:-1])) == s["values_tried"]  # every value once, then the final
    assert (s["added_below"] > 0) == (widened == "below")
    assert (s["added_above"] > 0) == (widened == "above")


def test_one_standard_error_rule_takes_the_largest_weight_the_views_cannot_tell_apart():
    """Held-out PSNR rising a little as the weight falls (as weaker regularisation keeps
    improving projection prediction): the best is the smallest weight, but the one-SE rule
    takes the largest weight within one standard error of it, computed from the best
    state's per-view PSNRs, and widens upwards only when that one sits at the top."""
    case, x = small_case()
    ramp = np.linspace(0, 1, 12, dtype=np.float32)[:, None, None] * np.ones((12,) * 3,
                                                                             np.float32)

    def run(proj, geo, n_iter, callback, progress, lam):
        # error grows with log10(lam): smaller weights predict the held-out views better
        vol = x + (0.02 + 0.01 * (math.log10(lam) + 4)) * ramp
        for it in range(n_iter):
            if callback(it, vol):
                break
        return vol

    grid = LogGrid("lam", [0.001, 0.003, 0.01], max_extend=3, rule="one_se")
    _, info = run_heldout(case, run, grid, project=forward_project, max_sweeps=3, name="t",
                          progress=False)
    cands = {c["setting"]["lam"]: c for c in info["candidates"]}
    best = max(cands.values(), key=lambda c: c["heldout_psnr"])
    assert best["setting"]["lam"] == min(cands)              # plain argmax: the lowest
    views = np.asarray(dict(map(tuple, best["heldout_psnr_views"]))[best["kept_sweep"]])
    se = np.std(views, ddof=1) / np.sqrt(len(views))
    assert best["one_se"]["standard_error_db"] == pytest.approx(se)
    within = [lam for lam, c in cands.items() if c["heldout_psnr"] >= best["heldout_psnr"] - se]
    chosen = info["chosen"]["setting"]["lam"]
    assert chosen == max(within) and chosen > best["setting"]["lam"]
    assert info["search"]["rule"] == "one standard error" and "one standard error" in info["why"]
    # the plain rule on the same runs widens downwards to the smallest weight instead
    grid = LogGrid("lam", [0.001, 0.003, 0.01], max_extend=3)
    _, plain = run_heldout(case, run, grid, project=forward_project, max_sweeps=3, name="t",
                           progress=False)
    assert plain["chosen"]["setting"]["lam"] == min(plain["search"]["values_tried"])
    assert not plain["search"]["interior"] and plain["search"]["added_below"] == 3


def _candidate(lam, residuals):
    """A decision run's record: residuals [sweep, held-out MSE, fitted-view MSE]."""
    return {"setting": {"lam": lam}, "residuals": [list(r) for r in residuals],
            "history": [[s, -10 * math.log10(h)] for s, h, _ in residuals]}


def test_morozov_takes_the_largest_weight_that_fits_the_data_to_their_noise():
    """Hand-made runs from one start (sweep 0): the noise level is the lowest held-out
    residual of any state (0.9 here, lam 0.003's sweep 10); the settled fitted residuals
    0.5, 0.8, 1.2 put the cut between 0.003 and 0.01; each weight keeps its sweep of lowest
    held-out residual, the start included (lam 0.01: its runs only got worse)."""
    from mi_grg.protocol.heldout import _choose
    start = (0, 1.0, 1.1)
    cands = [_candidate(0.01, [start, (5, 1.05, 1.15), (10, 1.1, 1.2)]),
             _candidate(0.001, [start, (5, 0.95, 0.7), (10, 0.97, 0.5)]),
             _candidate(0.003, [start, (5, 0.92, 0.9), (10, 0.9, 0.8)])]
    chosen, noise = _choose(cands, False, "morozov", from_start=True)
    assert noise == 0.9
    assert cands[chosen]["setting"]["lam"] == 0.003 and cands[chosen]["kept_sweep"] == 10
    assert [c["kept_sweep"] for c in cands] == [0, 5, 10]
    assert [c["settled_fit_mse"] for c in cands] == [1.2, 0.5, 0.8]
    assert cands[chosen]["heldout_psnr"] == pytest.approx(-10 * math.log10(0.9))
    # no weight fits the data to the noise level: the smallest, at its best sweep
    worse = [_candidate(0.01, [(5, 1.0, 3.0)]), _candidate(0.001, [(5, 2.0, 2.0)])]
    chosen, noise = _choose(worse, False, "morozov")
    assert noise == 1.0 and worse[chosen]["setting"]["lam"] == 0.001
    from mi_grg.protocol.heldout import _why
    assert _why(worse[chosen], [1], 2, noise, 5, 9).startswith("the smallest of 2 weight(s)")
    assert _why(cands[2], [1], 3, 0.9, 10, 9).startswith("the largest of 3 weight(s)")
    with pytest.raises(ValueError, match="rule must be one of"):
        LogGrid("lam", [0.001, 0.01], rule="lowest")


def test_morozov_search_widens_past_a_top_weight_that_still_fits():
    """Every weight of the grid fits the data below the noise level: the search widens
    upwards until a weight does not, and takes the one below it (interior)."""
    case, x = small_case()
    rng = np.random.default_rng(0)
    case = Case(geometry=case.geometry, vol_gt=None,
                train=case.train + 0.05 * rng.standard_normal(case.train.shape).astype(
                    np.float32))
    ramp = np.linspace(0, 1, 12, dtype=np.float32)[:, None, None] * np.ones((12,) * 3,
                                                                             np.float32)
    ran = []

    def run(proj, geo, n_iter, callback, progress, lam):
        # the residual grows with the weight: a bias of lam x ramp, none below 0.1
        vol = x + 3.0 * max(lam - 0.1, 0.0) * ramp
        for it in range(n_iter):
            ran.append(lam)
            if callback(it, vol):
                break
        return vol

    grid = LogGrid("lam", [0.001, 0.01], max_extend=4, rule="morozov")
    _, info = run_heldout(case, run, grid, project=forward_project, max_sweeps=4, name="t",
                          oracle=False, progress=False)
    s = info["search"]
    assert s["values_tried"] == pytest.approx([0.001, 0.01, 0.1, 1.0])
    assert s["chosen"] == pytest.approx(0.1) and s["interior"]
    assert s["rule"] == "Morozov's discrepancy principle" and "Morozov" in info["why"]
    assert sum(abs(v - 1.0) < 1e-9 for v in ran) == 4     # every candidate ran to the cap
    assert info["morozov"]["noise_mse"] == pytest.approx(0.05 ** 2, rel=0.2)


def test_weight_search_says_when_its_widening_is_spent():
    case, x = small_case()
    run, _ = weighted_method(x, 1e-9)
    _, info = run_heldout(case, run, LogGrid("lam", [0.001, 0.01], max_extend=2),
                          project=forward_project, max_sweeps=3, name="t", progress=False)
    s = info["search"]
    assert not s["interior"] and s["added_below"] == 2
    assert s["chosen"] == pytest.approx(1e-5) and s["values_tried"][0] == s["chosen"]


@pytest.mark.parametrize("values, match", [([0.01], "at least two"), ([0.01, -1], "> 0"),
                                           ([0.01, 0.01], "distinct"), ([0, 0.1], "> 0")])
def test_log_grid_bad_input_names_the_weight(values, match):
    with pytest.raises(ValueError, match=f"lam: .*{match}"):
        LogGrid("lam", values)


def test_methods_reject_bad_protocol_options_in_one_line():
    from mi_grg.classical.iterative import reconstruct_asd_pocs
    from mi_grg.classical.pdhg import reconstruct_pdhg
    case, _ = small_case()
    bad = [(reconstruct_pdhg, {"lam": -0.1}, "lam must be"),
           (reconstruct_pdhg, {"lam": [0.01]}, "at least two"),
           (reconstruct_asd_pocs, {"alpha": [0.002, -1.0]}, "alpha must be"),
           (reconstruct_pdhg, {"holdout_every": 9}, "holdout_every=9 leaves 1 of 9"),
           (reconstruct_asd_pocs, {"holdout_every": 20}, "holdout_every=20 leaves")]
    for fn, opts, match in bad:
        with pytest.raises(ValueError, match=match) as e:
            fn(case, progress=False, **opts)
        assert "\n" not in str(e.value)


def test_decision_split_needs_two_views_on_each_side():
    assert [len(v) for v in decision_split(25, 8, "m")] == [21, 4]
    assert [len(v) for v in decision_split(4, 2, "m")] == [2, 2]
    for n, every in ((25, 25), (3, 2), (2, 1)):
        with pytest.raises(ValueError, match=f"m: holdout_every={every} leaves"):
            decision_split(n, every, "m")


def test_discrepancy_stops_at_the_first_crossing_neither_first_nor_last():
    # held-out residuals: the noise level is their minimum (0.9); the fitted residual
    # falls through it at iteration 30 (of 10 .. 60)
    held = [1.6, 1.1, 0.95, 0.9, 0.92, 0.97]
    fit = [(10, 2.0), (20, 1.2), (30, 0.85), (40, 0.6), (50, 0.4), (60, 0.3)]
    noise = noise_level(held)
    assert noise == 0.9
    assert discrepancy_stop(fit, noise) == 30
    assert discrepancy_stop(fit, noise, tau=1.5) == 20      # tau scales the level
    assert discrepancy_stop(fit, 0.1) is None               # never reached
    with pytest.raises(ValueError, match="held-out residuals"):
        noise_level([0.5, float("nan")])
    with pytest.raises(ValueError, match="tau"):
        discrepancy_stop(fit, noise, tau=0)


# ------------------------------------------------------------------ layering
#: Each subpackage (or top-level module) may import only from those listed before it.
#: The Mitsuba plugins (plugins/, installed as mi_grg.plugins) parse with data and project
#: with core; mi_grg.variant reaches them only through the hook the package gives it.
LAYERS = [{"_llvm", "variant"}, {"core"}, {"data"}, {"plugins"}, {"evaluation"},
          {"protocol"}, {"classical"}, {"training"}, {"methods"}, {"lab"}, {"cli"}]


def _unit(module: str) -> str:
    return module.split(".")[1] if module.startswith("mi_grg.") else module


def test_subpackages_import_only_from_lower_layers():
    """Every import in mi_grg/ and plugins/ (function-local ones included) goes to a lower
    layer or its own: no cycle between subpackages."""
    rank = {u: i for i, layer in enumerate(LAYERS) for u in layer}
    wrong = []
    paths = [(p, p.relative_to(ROOT / "mi_grg").parts) for p in (ROOT / "mi_grg").rglob("*.py")]
    paths += [(p, ("plugins", p.name)) for p in (ROOT / "plugins").glob("*.py")]
    for path, rel in paths:
        src = rel[0] if len(rel) > 1 else rel[0][:-3]
        if src == "__init__":
            continue      # the package: its lazy table names every layer, and it hands the
                          # plugins' registration to mi_grg.variant
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([node.module] if isinstance(node, ast.ImportFrom) and node.module
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            for name in names:
                if not name.startswith("mi_grg."):
                    continue
                dst = _unit(name)
                if dst != src and rank[dst] >= rank[src]:
                    wrong.append(f"{path.relative_to(ROOT)}: {src} -> {dst}")
    assert not wrong, wrong


# ------------------------------------------------------------------ no leakage
def _poisoned(case: Case, seed: int) -> Case:
    """The same case with its ground truth and test views replaced by noise."""
    rng = np.random.default_rng(seed)
    return Case(geometry=case.geometry, train=case.train, test_angles=case.test_angles,
                test=rng.random(case.test.shape).astype(np.float32),
                vol_gt=rng.random(case.vol_gt.shape).astype(np.float32),
                info=case.info)


LEAK_RUNS = [("fdk", {}), ("sart", {"n_iter": 4}), ("asd-pocs", {"n_iter": 3}),
             ("pdhg", {"n_iter": 10}),
             ("r2", {"iterations": 60, "eval_every": 10, "densify_interval": 20,
                     "n_points": 300, "holdout_every": 4}),
             # long enough for a state kept before the held-out views join: the TV
             # refinement (gr's default) then decides too
             ("gr", {"iterations": 150, "eval_every": 10, "densify_interval": 20,
                     "n_points": 300, "holdout_every": 4, "log_3d_every": 10})]


@pytest.mark.parametrize("method, opts", LEAK_RUNS, ids=[m for m, _ in LEAK_RUNS])
def test_no_decision_reads_the_ground_truth_or_the_test_views(method, opts):
    """Each method's volume and every decision it records are the same whatever the
    ground truth and test views hold (they may only be scored against)."""
    import drjit as dr
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=16, det=24, views=12)
    case = simulate_case("shepp", geo, default_test_angles(4), NoiseModel(), seed=0)
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        runs = [mi_grg.reconstruct(c, method, **opts, **({} if method == "fdk" else
                                                          {"progress": False}))
                for c in (case, _poisoned(case, 1))]
    finally:
        dr.set_thread_count(threads)
    (v1, m1), (v2, m2) = runs

    def timeless(x):   # wall-clock fields differ between any two runs
        if isinstance(x, dict):
            return {k: timeless(v) for k, v in x.items() if "seconds" not in k}
        return [timeless(v) for v in x] if isinstance(x, list) else x
    np.testing.assert_array_equal(v1, v2)
    assert m1["psnr_3d"] != m2["psnr_3d"]          # the poison was seen by the scoring
    i1, i2 = m1.get("method_info") or {}, m2.get("method_info") or {}
    for key in ("chosen", "candidates", "search", "discrepancy", "held_out_views",
                "iterations_run", "kept_iteration", "best_iteration", "stopped_by", "views",
                "refine"):
        assert timeless(i1.get(key)) == timeless(i2.get(key)), key
    if method == "gr":
        assert "lam" in i1["refine"], i1["refine"]


def test_gr_paper_preset_holds_the_papers_configuration():
    """scenes/gr_paper.xml: GR-Gaussian as the paper sets it (Sec. 4.1.2), every field
    written, whatever gr's default becomes."""
    from mi_grg.training.config import FLAT_KEYS, make_config, read_config_xml
    method, values = read_config_xml(ROOT / "scenes" / "gr_paper.xml")
    assert method == "gr" and set(values) == set(FLAT_KEYS)
    cfg = make_config("gr", ROOT / "scenes" / "gr_paper.xml")
    paper = {"k": 6, "lambda_lap": 8e-4, "lambda_g": 1e-4, "use_pga": True,
             "use_graph_field": True, "sigma_d": 3.0, "sigma_d_grid": 256, "init": "fdk",
             "n_points": 50000, "init_tau": 0.001, "data_loss": "l1", "lambda_ssim": 0.25,
             "lambda_tv": 0.05, "tv_block": 32, "densify_grad_threshold": 5e-5,
             "stop_drop": 0.005, "refine": "none"}
    assert {k: cfg.to_flat()[k] for k in paper} == paper


def test_pdhg_init_reads_only_the_fitted_views():
    """gr's De-Init from PDHG (``init="pdhg"``): PDHG decides on the fitted views' own
    split, so the run's held-out views (replaced by noise here) change nothing at the
    start, and what PDHG chose is recorded."""
    import drjit as dr
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    geo = default_geometry(n=16, det=24, views=12)
    case = simulate_case("shepp", geo, default_test_angles(2), NoiseModel(), seed=0)
    cfg = make_config("gr", init="pdhg", iterations=20, n_points=300, holdout_every=4)
    poisoned = Case(geometry=case.geometry, train=case.train.copy())
    starts = []
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        for c in (case, poisoned):
            t = Trainer(c, cfg, progress=False)
            if c is poisoned:
                assert t.held_idx.tolist() == starts[0][1]
            else:
                c_held = t.held_idx
                poisoned.train[c_held] = np.random.default_rng(0).random(
                    poisoned.train[c_held].shape).astype(np.float32)
            starts.append(({k: np.asarray(v) for k, v in t.state.raw.items()},
                           t.held_idx.tolist(), t.init_info))
    finally:
        dr.set_thread_count(threads)
    (a, held, info), (b, _, _) = starts
    assert len(held) == 3 and info["volume"] == "pdhg" and "lam" in info["pdhg"]["chosen"]["setting"]
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
