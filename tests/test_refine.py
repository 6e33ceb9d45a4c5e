"""The TV refinement of a trained volume (``refine="tv"``): PDHG's warm start, the held-out
decision that starts from another method's volume (the start is itself a candidate), and
gr's refine option end to end."""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

import mi_grg
from mi_grg.classical.pdhg import PDHG, reconstruct_pdhg
from mi_grg.core.joseph import forward_project
from mi_grg.evaluation.metrics import psnr_3d
from mi_grg.protocol.heldout import run_heldout
from tests.test_heldout import RAMP, noisy_ellipsoids, small_case


@pytest.fixture(autouse=True)
def _llvm():
    mi_grg.set_variant("llvm_ad_mono")


def test_warm_start_is_clipped_and_its_duals_are_at_their_fixed_point():
    case, x = small_case()
    start = x - 0.3                               # negative voxels: outside the box
    s = PDHG(case.train, case.geometry, case.geometry.angles, lam=0.01, init=start)
    np.testing.assert_array_equal(np.asarray(s.x.numpy()).reshape(x.shape),
                                  np.maximum(start, 0))
    # y1 = A x - b is the data term's fixed point: (y1 + sigma r) / (1 + sigma) = y1
    r = s.A.forward(s.x, s.angles) - s.b
    np.testing.assert_allclose(s.y1.numpy(), r.numpy(), rtol=1e-6, atol=1e-7)
    # |y2| = lam / mu wherever the volume is not flat
    norm = np.sqrt(sum(np.asarray(c.numpy()) ** 2 for c in s.y2))
    assert np.max(norm) == pytest.approx(s.lam_abs / s.mu, rel=1e-5)


def test_warm_start_at_the_minimiser_stays_there_and_cold_duals_do_not():
    """From a converged solution, warm duals keep x near it; zero duals move it away (the
    transient a held-out decision would read as a loss of the start's quality)."""
    case, _ = small_case()
    geo = case.geometry
    sol = PDHG(case.train, geo, geo.angles, lam=0.01)
    for _ in range(1500):
        sol.step()
    x_star = np.asarray(sol.x.numpy()).reshape(geo.nVoxel)
    moved = {}
    for warm in (True, False):
        s = PDHG(case.train, geo, geo.angles, lam=0.01, init=x_star, norm_A=sol.norm_A)
        if not warm:
            s.y1 = dr.zeros(mi.Float, dr.width(s.b))
            s.y2 = [dr.zeros(mi.Float, s.A.n_vox) for _ in range(3)]
        for _ in range(5):
            s.step()
        moved[warm] = float(np.abs(np.asarray(s.x.numpy()).reshape(geo.nVoxel) - x_star).mean())
    assert moved[True] < 0.3 * moved[False], moved


def _scripted(log):
    """A method that worsens its start by a ramp per sweep (no sweep beats the start)."""
    def run(proj, geo, n_iter, callback, progress, w, init):
        log.append((proj.shape[0], init))
        for it in range(n_iter):
            vol = init + 0.05 * w * (it + 1) * RAMP
            if callback(it, vol):
                break
        return vol
    return run


def test_start_wins_when_no_sweep_improves_it_and_is_returned_unchanged():
    case, x_true = small_case()
    log = []
    final_start = x_true + 0.01                   # a different array from the decision's
    vol, info = run_heldout(case, _scripted(log), [{"w": 1.0}, {"w": 2.0}], max_sweeps=20,
                            name="t", project=forward_project, oracle=False,
                            start=(x_true, final_start), progress=False)
    assert info["chosen"]["sweeps"] == 0
    np.testing.assert_array_equal(vol, final_start)
    # the decision runs started from the decision start, on the fitted views only
    assert [n for n, _ in log] == [9 - len(info["held_out_views"])] * 2
    assert all(init is x_true for _, init in log)
    with pytest.raises(ValueError, match="start must be"):
        run_heldout(case, _scripted([]), [{"w": 1.0}], max_sweeps=5, name="t",
                    project=forward_project, start=(x_true,), progress=False)


@pytest.mark.parametrize("lam_rule", [None, "morozov"])
def test_refinement_removes_voxel_noise_the_views_do_not_constrain(lam_rule):
    """Ground truth plus voxel-scale noise as the start (what gr leaves on dense volumes):
    PDHG from it, decided on held-out views, gains several dB; from the exact volume with
    exact data nothing improves the held-out views and the start comes back unchanged.
    Both weight rules (refine="tv" uses Morozov's)."""
    case, _ = noisy_ellipsoids(n=24, sigma=0.02)
    gt = case.vol_gt
    noisy = gt + 0.15 * np.random.default_rng(0).standard_normal(gt.shape).astype(np.float32)
    vol, info = reconstruct_pdhg(case, start=(noisy, noisy), oracle=False, progress=False,
                                 lam_rule=lam_rule)
    assert info["chosen"]["sweeps"] > 0
    assert psnr_3d(vol, gt) > psnr_3d(noisy, gt) + 3.0, info["chosen"]

    exact = case.__class__(geometry=case.geometry, train=forward_project(gt, case.geometry),
                           vol_gt=gt)
    vol, info = reconstruct_pdhg(exact, start=(gt, gt), oracle=False, progress=False,
                                 lam_rule=lam_rule)
    assert info["chosen"]["sweeps"] == 0
    np.testing.assert_array_equal(vol, gt)
    with pytest.raises(ValueError, match="stop='heldout'"):
        reconstruct_pdhg(case, stop="none", start=(gt, gt), progress=False)
    with pytest.raises(ValueError, match="leaves nothing to choose"):
        reconstruct_pdhg(case, lam=0.01, lam_rule="morozov", progress=False)
    with pytest.raises(ValueError, match="lam_rule must be one of"):
        reconstruct_pdhg(case, lam_rule="lowest", progress=False)


def test_gr_refine_option(tiny_case, capsys, tmp_path):
    """refine="tv" runs after training and records its decision; what the run exports is
    what it scores (gaussians.npz voxelised is vol_pred); refine_output="voxels" scores the
    grid and exports the field under a name that says so; without held-out views it says it
    was skipped; an unknown mode is a one-line error naming the option."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.voxelizer import voxelize
    from mi_grg.methods import reconstruct
    from mi_grg.training.config import ConfigError
    opts = dict(iterations=300, n_points=300, eval_every=200, holdout_every=3,
                progress=False)
    vol, m = reconstruct(tiny_case, "gr", out_dir=tmp_path / "g", **opts)
    info = m["method_info"]
    r = info["refine"]
    assert r["lam"] == info["config"]["refine_lam"] and 0 <= r["iterations"] <= r["cap"]
    assert r["curve"][0][0] == 0 and r["iterations"] in [c[0] for c in r["curve"]]
    assert r["heldout_mse"]["refined"] <= r["heldout_mse"]["start"]
    assert info["result"]["export"] == {"stem": "gaussians", "is_result": True}
    g = Gaussians.load_npz(tmp_path / "g" / "gaussians.npz")
    extent = info["extent"]
    np.testing.assert_allclose(voxelize(g, tiny_case.geometry, extent=extent), vol,
                               rtol=1e-5, atol=1e-6)
    grid, m = reconstruct(tiny_case, "gr", out_dir=tmp_path / "v", refine_output="voxels",
                          **opts)
    assert m["method_info"]["result"]["export"]["is_result"] is False
    assert (tmp_path / "v" / "gaussians_before_voxel_step.npz").exists()
    assert not (tmp_path / "v" / "gaussians.npz").exists()
    from mi_grg.evaluation.crosscheck_run import run_scene
    with pytest.raises(FileNotFoundError, match="scored a voxel grid"):
        run_scene(tmp_path / "v", tmp_path / "render")
    if m["method_info"]["refine"]["iterations"] > 0:
        assert not np.array_equal(grid, vol)
    capsys.readouterr()
    # without held-out views a decision run needs the stop rule's split: 6 views are too few
    _, m = reconstruct(tiny_case, "gr", **{**opts, "holdout_every": 0})
    assert "holdout_every=0" in m["method_info"]["refine"]["skipped"]
    assert "refine=tv did nothing: no held-out views" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="refine must be one of"):
        reconstruct(tiny_case, "gr", refine="blur", **opts)
    with pytest.raises(ConfigError, match="refine_output must be one of"):
        reconstruct(tiny_case, "gr", refine_output="grid", **opts)


def test_refine_anchor_is_the_held_out_choice(tiny_case, monkeypatch):
    """refine_anchor="auto" decides the length with the anchor and without it and keeps the
    form with the lower held-out residual (recorded); "off" never builds anchored data;
    an unknown value is a one-line error naming the option."""
    from mi_grg.methods import reconstruct
    from mi_grg.training import result
    from mi_grg.training.config import ConfigError
    from mi_grg.training import densify
    opts = dict(iterations=300, n_points=300, eval_every=200, holdout_every=3,
                progress=False)
    # (the tiny run's count grows to the end of its window: its demand is declared met
    # here; test_auto_refines_plain_where_densification_fell_short covers the other case)
    met = {"growth": 0.0, "cap_share": 0.5, "met": True}
    monkeypatch.setattr(densify, "demand", lambda log, window: met)
    _, m = reconstruct(tiny_case, "gr", **opts)
    r = m["method_info"]["refine"]
    a = r["anchor"]
    assert a["rule"] == "auto" and set(a["heldout_mse"]) == {"anchored", "plain"}
    assert a["densification"] == met
    mse = a["heldout_mse"]
    assert a["anchored"] == (mse["anchored"] <= mse["plain"])
    assert r["heldout_mse"]["minimum"] == min(mse.values())
    for form, curve in a["curves"].items():     # both curves recorded, the chosen one's too
        assert min(m for _, m in curve) == mse[form] and curve[0][0] == 0
    assert a["curves"]["anchored" if a["anchored"] else "plain"] == r["curve"]
    # the tiles (8 of 3 pixels a side here) weigh every pixel alike: the standardised
    # difference has the sign of the residuals' difference
    assert np.sign(a["z"]) == np.sign(mse["anchored"] - mse["plain"]) != 0

    def no_anchor(*args, **kwargs):
        raise AssertionError("refine_anchor=off built anchored data")
    monkeypatch.setattr(result, "anchored_data", no_anchor)
    _, m = reconstruct(tiny_case, "gr", refine_anchor="off", **opts)
    a = m["method_info"]["refine"]["anchor"]
    assert a["anchored"] is False and list(a["heldout_mse"]) == ["plain"] and a["z"] is None
    with pytest.raises(ConfigError, match="refine_anchor must be one of"):
        reconstruct(tiny_case, "gr", refine_anchor="maybe", **opts)


def test_auto_refines_plain_where_densification_fell_short(tiny_case, monkeypatch):
    """refine_anchor="auto" on a run whose densification did not meet the field's demand
    (mi_grg.training.densify.demand on the run's own log and window) decides the plain
    length only and records the verdict; the tiny run's count still grows at the end of
    its window."""
    from mi_grg.methods import reconstruct
    from mi_grg.training import densify, result
    forms, verdicts = [], []
    real_decide, real_demand = result.decide_length, densify.demand

    def spy_decide(*args, anchored=True, **kwargs):
        forms.append(anchored)
        return real_decide(*args, anchored=anchored, **kwargs)

    def spy_demand(log, window):
        verdicts.append(real_demand(log, window))
        return verdicts[-1]
    monkeypatch.setattr(result, "decide_length", spy_decide)
    monkeypatch.setattr(densify, "demand", spy_demand)
    _, m = reconstruct(tiny_case, "gr", iterations=300, n_points=300, eval_every=200,
                       holdout_every=3, progress=False)
    a = m["method_info"]["refine"]["anchor"]
    assert len(verdicts) == 1 and not verdicts[0]["met"]
    assert verdicts[0]["growth"] >= densify.DEMAND_GROWTH or \
        verdicts[0]["cap_share"] >= densify.DEMAND_CAP
    assert a["densification"] == verdicts[0]
    assert forms == [False] and a["anchored"] is False and list(a["heldout_mse"]) == ["plain"]
    assert a["z"] is None


def test_without_held_out_views_a_decision_run_decides(tiny_case, capsys, monkeypatch):
    """holdout_every=0: the run trains every view from the start; a second run with the stop
    rule's split (here one view in 3, as 6 views allow) gives the kept state the length is
    decided from, and the first run's own final field is what is refined."""
    import dataclasses

    from mi_grg.methods import reconstruct
    from mi_grg.protocol import early_stop
    from mi_grg.training import result
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    monkeypatch.setattr(early_stop, "STOP_RULE",
                        dataclasses.replace(early_stop.STOP_RULE, holdout_every=3))
    opts = dict(iterations=300, n_points=300, eval_every=200)
    _, m = reconstruct(tiny_case, "gr", holdout_every=0, progress=False, **opts)
    r = m["method_info"]["refine"]
    assert "skipped" not in r and r["decision_run"]["held_out_views"] == [1, 4]
    assert r["decision_run"]["kept_iteration"] <= 200
    assert "a decision run (holdout_every=3)" in capsys.readouterr().err
    # what decides: the decision run's kept field, on its held-out views; what is refined:
    # the run's own final field
    seen = {}
    real = result.decide_length

    def spy(trainer, kept, progress=True, anchored=True, start=None, norm_A=None):
        seen.update(held=list(trainer.held_idx), kept=result.field_volume(trainer, kept))
        # the start is the kept field's voxelisation (to the scatter-adds' thread order)
        np.testing.assert_allclose(start, seen["kept"], rtol=1e-5,
                                   atol=1e-6 * float(np.abs(seen["kept"]).max()))
        return real(trainer, kept, progress, anchored, start, norm_A=norm_A)
    monkeypatch.setattr(result, "decide_length", spy)
    t = Trainer(tiny_case, make_config("gr", holdout_every=0, **opts), progress=False)
    t.run()
    _, _, info = result.finish(t, progress=False)
    assert seen["held"] == [1, 4] and info["refine"]["decision_run"]["held_out_views"] == [1, 4]
    final = result.field_volume(t, result.averaged_field(t, t.field_gaussians()))
    assert not np.allclose(seen["kept"], final)
    budget = reconstruct(tiny_case, "gr", holdout_every=0, progress=False,
                         time_budget=30, n_points=300)[1]["method_info"]["refine"]
    assert "time_budget" in budget["skipped"]
