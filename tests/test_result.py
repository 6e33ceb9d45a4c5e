"""A trained run's result (mi_grg.training.result, mi_grg.training.distill): the anchored
data give the field's start its own residual, the length is the held-out residual's
minimum, and a grid is fitted back into Gaussians."""
import numpy as np
import pytest

import mi_grg
from mi_grg.core.joseph import forward_project
from mi_grg.core.voxelizer import voxelize


@pytest.fixture(autouse=True)
def _llvm():
    mi_grg.set_variant("llvm_ad_mono")


@pytest.fixture(scope="module")
def trained(tiny_case):
    from mi_grg.training.config import make_config
    from mi_grg.training.trainer import Trainer
    mi_grg.set_variant("llvm_ad_mono")
    t = Trainer(tiny_case, make_config("gr", iterations=300, n_points=300, eval_every=200,
                                       holdout_every=3), progress=False)
    t.run()
    return t


def test_anchored_data_give_the_start_the_fields_own_residual(trained):
    """A V(G) - b' = P(G) - b on every view: the Joseph model's error on the field itself
    is not part of what the refinement fits (and without the anchor it would be)."""
    from mi_grg.training import result
    t = trained
    geo = t.case.geometry
    g = result.averaged_field(t, t.field_gaussians())
    vol = result.field_volume(t, g)
    views = np.arange(geo.n_views)
    b2 = result.anchored_data(t, g, vol, views)
    own = result.projections(t, g, views) - t.case.train
    joseph = forward_project(vol, geo, geo.angles) - t.case.train
    np.testing.assert_allclose(forward_project(vol, geo, geo.angles) - b2, own,
                               rtol=1e-4, atol=1e-5 * np.abs(t.case.train).max())
    assert np.abs(joseph - own).max() > 1e-3 * np.abs(t.case.train).max()


def test_length_is_the_held_out_fall_and_the_cap_is_said(trained, capsys, monkeypatch):
    """The length is the first check where the held-out residual has made the share
    refine_fall of its fall to the curve's minimum (1, refine_tol 0: the minimum itself), from the same
    curve; reaching the cap is said."""
    from mi_grg.training import result
    t = trained
    kept = result.averaged_field(t, t.field_gaussians(t.state.kept_raw, t.state.kept_density_scale))
    start = result.field_volume(t, kept)
    monkeypatch.setattr(t.cfg.protocol, "refine_fall", 1.0)
    monkeypatch.setattr(t.cfg.protocol, "refine_tol", 0.0)
    d = result.decide_length(t, kept, progress=False, start=start, patience=0)
    its = [c[0] for c in d["curve"]]
    assert its[0] == 0 and its[-1] == t.cfg.protocol.refine_max_iterations
    assert d["iterations"] == min(d["curve"], key=lambda c: c[1])[0]
    assert d["heldout_mse"] == d["heldout_mse_chosen"] == min(c[1] for c in d["curve"])
    assert d["at_cap"] == (d["iterations"] == its[-1])
    m0, m_min = d["curve"][0][1], d["heldout_mse"]
    assert m0 > 1.05 * m_min           # the curve falls: a share of it is a real choice
    monkeypatch.setattr(t.cfg.protocol, "refine_fall", 0.5)
    h = result.decide_length(t, kept, progress=False, start=start, patience=0)
    # the same solver and checks (PDHG's sums run in thread order: last bits differ)
    np.testing.assert_allclose(np.asarray(h["curve"]), np.asarray(d["curve"]), rtol=1e-6)
    m0, m_min = h["curve"][0][1], h["heldout_mse"]
    target = m0 - 0.5 * (m0 - m_min)
    before = [m for it, m in h["curve"] if it < h["iterations"]]
    assert h["heldout_mse_chosen"] <= target and all(m > target for m in before)
    assert h["iterations"] < d["iterations"]
    # a cap of one check: the minimum is at the cap whenever one step helps; it is said
    monkeypatch.setattr(t.cfg.protocol, "refine_max_iterations", 5)
    field = result.averaged_field(t, t.field_gaussians())
    monkeypatch.setattr(result, "decide_length", lambda *a, **k: {
        "iterations": 5, "at_cap": True, "curve": [(0, 1.0), (5, 0.5)], "heldout_mse": 0.5,
        "heldout_mse_chosen": 0.5, "heldout_tiles": np.full(4, 0.5), "norm_A": None,
        "seconds": 0.0})
    vol, g, info = result.refine_field(t, field, result.field_volume(t, field), kept, t,
                                       progress=False)
    assert info["at_cap"] and "a 4x higher cap measured no better" in capsys.readouterr().err
    # (the voxelizer's scatter-adds sum in thread order: two calls differ in the last bits)
    np.testing.assert_allclose(result.field_volume(t, g), vol, rtol=1e-5,
                               atol=1e-6 * float(np.abs(vol).max()))


def test_the_length_decision_stops_patience_checks_after_its_last_minimum(trained,
                                                                        monkeypatch):
    """With ``patience`` P the decision's curve is the full curve's beginning, ending P
    checks after its last new minimum (or at the cap); where the full curve's minimum lies
    in it, the length is the full decision's. Without ``patience`` it is ``PATIENCE``."""
    from mi_grg.training import result
    t = trained
    kept = result.averaged_field(t, t.field_gaussians(t.state.kept_raw, t.state.kept_density_scale))
    start = result.field_volume(t, kept)
    monkeypatch.setattr(t.cfg.protocol, "refine_fall", 1.0)
    full = result.decide_length(t, kept, progress=False, start=start, patience=0)
    mse = [m for _, m in full["curve"]]
    assert any(b >= a for a, b in zip(mse, mse[1:]))   # not falling throughout: P can stop it
    lengths = {}
    for p in (1, 2, 3):
        d = result.decide_length(t, kept, progress=False, start=start, patience=p)
        n = lengths[p] = len(d["curve"])
        # the same solver and checks (PDHG's sums run in thread order: last bits differ)
        np.testing.assert_allclose(np.asarray(d["curve"]), np.asarray(full["curve"][:n]),
                                   rtol=1e-6)
        best = min(range(n), key=lambda i: d["curve"][i][1])
        assert n - 1 - best == p or d["curve"][-1][0] == full["curve"][-1][0]
        if min(mse[:n]) == min(mse):
            assert d["iterations"] == full["iterations"]
    assert lengths[1] < len(full["curve"]) and lengths[1] <= lengths[2] <= lengths[3]
    monkeypatch.setattr(result, "PATIENCE", 1)
    assert len(result.decide_length(t, kept, progress=False, start=start)["curve"]) == lengths[1]


def test_the_length_within_a_tolerance_of_the_minimum(trained, monkeypatch):
    """refine_tol: the length is the first check whose held-out residual is within that
    share of the curve's minimum (the same curve as without it); a tolerance above the
    whole fall means no refinement."""
    from mi_grg.training import result
    t = trained
    kept = result.averaged_field(t, t.field_gaussians(t.state.kept_raw, t.state.kept_density_scale))
    start = result.field_volume(t, kept)
    monkeypatch.setattr(t.cfg.protocol, "refine_fall", 1.0)
    d = result.decide_length(t, kept, progress=False, start=start, patience=0)
    m0, m_min = d["curve"][0][1], d["heldout_mse"]
    tol = 0.5 * (m0 / m_min - 1.0)          # half the fall, in shares of the minimum
    monkeypatch.setattr(t.cfg.protocol, "refine_tol", tol)
    h = result.decide_length(t, kept, progress=False, start=start, patience=0)
    np.testing.assert_allclose(np.asarray(h["curve"]), np.asarray(d["curve"]), rtol=1e-6)
    before = [m for it, m in h["curve"] if it < h["iterations"]]
    assert h["heldout_mse_chosen"] <= (1 + tol) * h["heldout_mse"]
    assert before and all(m > (1 + tol) * h["heldout_mse"] for m in before)
    assert 0 < h["iterations"] < d["iterations"]
    monkeypatch.setattr(t.cfg.protocol, "refine_tol", 1.01 * (m0 / m_min - 1.0))
    assert result.decide_length(t, kept, progress=False, start=start,
                                patience=0)["iterations"] == 0


def test_the_two_length_decisions_share_one_power_iteration(trained, monkeypatch):
    """Both forms' decisions run PDHG on the same fitted views: the first one's ||A||
    serves the second, which then decides as it would with its own power iteration."""
    from mi_grg.classical import pdhg as pdhg_module
    from mi_grg.training import result
    t = trained
    kept = result.averaged_field(t, t.field_gaussians(t.state.kept_raw, t.state.kept_density_scale))
    start = result.field_volume(t, kept)
    own = result.decide_length(t, kept, progress=False, anchored=False, start=start)
    calls = []
    norm = pdhg_module.operator_norm
    monkeypatch.setattr(pdhg_module, "operator_norm",
                        lambda *a, **k: calls.append(1) or norm(*a, **k))
    given = result.decide_length(t, kept, progress=False, anchored=False, start=start,
                                 norm_A=own["norm_A"])
    assert not calls and given["norm_A"] == own["norm_A"] > 0
    assert given["iterations"] == own["iterations"]
    np.testing.assert_allclose(np.asarray(given["curve"]), np.asarray(own["curve"]),
                               rtol=1e-6)
    monkeypatch.setattr(t.cfg.protocol, "refine_anchor", "auto")
    monkeypatch.setattr(t.cfg.protocol, "refine_output", "voxels")
    from mi_grg.training import densify     # (both forms: the tiny run's count still grows)
    monkeypatch.setattr(densify, "demand", lambda log, window: {"met": True})
    field = result.averaged_field(t, t.field_gaussians())
    vol, _, info = result.refine_field(t, field, result.field_volume(t, field), kept, t,
                                       progress=False)
    assert set(info["anchor"]["curves"]) == {"anchored", "plain"}
    # one power iteration for the two decisions, one for the final refinement on every view
    assert len(calls) == (2 if info["iterations"] else 1)


def test_tile_means_are_the_tiles_brute_force_means():
    """Each view's detector cut into TILES x TILES tiles (row i in tile i * T // nv, and
    so for columns; fewer tiles than pixels never), each tile's mean in view-major order."""
    from mi_grg.training import result
    rng = np.random.default_rng(0)
    for shape in [(3, 24, 24), (2, 13, 29), (1, 5, 40)]:
        r2 = rng.random(shape)
        _, nv, nu = shape
        tv, tu = min(result.TILES, nv), min(result.TILES, nu)
        ref = [np.mean([r2[w, i, j] for i in range(nv) for j in range(nu)
                        if i * tv // nv == a and j * tu // nu == b])
               for w in range(shape[0]) for a in range(tv) for b in range(tu)]
        np.testing.assert_allclose(result.tile_means(r2), ref, rtol=1e-12)


def test_difference_z_is_the_mean_difference_over_its_standard_error():
    from mi_grg.training import result
    rng = np.random.default_rng(1)
    a, b = rng.random(50), rng.random(50)
    d = a - b
    ref = d.mean() / (np.sqrt(np.sum((d - d.mean()) ** 2) / 49) / np.sqrt(50))
    assert result.difference_z(a, b) == pytest.approx(ref, rel=1e-12)
    assert result.difference_z(b, a) == pytest.approx(-ref, rel=1e-12)
    assert result.difference_z(a, a) == 0.0
    assert result.difference_z(a + 1.0, a) > 1e6      # a constant offset: no scatter


def test_fit_to_volume_recovers_a_field_from_a_perturbed_start(tiny_case):
    """The grid of known Gaussians, the fit started from them perturbed: its fidelity rises
    far above the start's and is what it reports."""
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.training.distill import fidelity_db, fit_to_volume
    geo = tiny_case.geometry
    rng = np.random.default_rng(1)
    n = 40
    lo = np.asarray(geo.sVoxel) * 0.3
    g = Gaussians.from_numpy(rng.uniform(-lo, lo, (n, 3)),
                             rng.uniform(0.08, 0.2, (n, 3)) * geo.sVoxel[0] / 2,
                             None, rng.uniform(0.2, 1.0, n))
    target = voxelize(g, geo, extent=3.0)
    a = g.numpy()
    start = Gaussians.from_numpy(a["positions"], a["scales"] * 1.15, a["rotations"],
                                 a["densities"] * 0.8)
    lr = {"positions": 2e-4, "raw_densities": 1e-2, "raw_scales": 5e-3,
          "raw_rotations": 1e-3}
    checks = []

    def on_check(it, g_it, db):
        # what the hook is told is that state's own fidelity
        assert fidelity_db(voxelize(g_it, geo, extent=3.0), target) == pytest.approx(db)
        checks.append((it, db))

    fit, info = fit_to_volume(start, geo, target, lr=lr, iterations=150, extent=3.0,
                              progress=False, on_check=on_check)
    got = fidelity_db(voxelize(fit, geo, extent=3.0), target)
    assert got == pytest.approx(info["fidelity_db"], abs=1e-6)
    assert got > info["fidelity_db_start"] + 10.0, info
    # every check reported, and the fit returned is the best of them
    assert [it for it, _ in checks] == list(range(25, info["iterations"] + 1, 25))
    assert info["fidelity_db"] == max(db for _, db in checks)
    with pytest.raises(ValueError, match="target has shape"):
        fit_to_volume(start, geo, target[:-1], lr=lr, iterations=5, extent=3.0)


@pytest.mark.parametrize("made_with", [0.0, 1.0, 2.0])
def test_held_out_blur_is_the_one_that_made_the_views(trained, monkeypatch, made_with):
    """field_blur="heldout" adds the share of BLUR_SHARES whose blur of the kept field fits
    the held-out views best: views made (noise-free) as the exact projections of the kept
    field blurred by a known share give that share, added to voxel_average's (which the
    views do not judge: judging base + share would pick made_with - 0.5)."""
    from mi_grg.core.voxel_average import convolve_gaussians, voxel_variance
    from mi_grg.training import result
    t = trained
    kept = t.field_gaussians(t.state.kept_raw, t.state.kept_density_scale)
    held = np.asarray(t.held_idx)
    box = voxel_variance(t.case.geometry, 1.0)
    train = t.case.train.copy()
    train[held] = result.projections(t, convolve_gaussians(kept, made_with * box), held)
    monkeypatch.setattr(t.case, "train", train)
    monkeypatch.setattr(t.cfg.protocol, "voxel_average", 0.5)
    monkeypatch.setattr(t.cfg.protocol, "field_blur", "heldout")
    share, rec = result.field_share(t)
    assert rec["added"] == made_with and share == 0.5 + made_with == rec["share"]
    mse = rec["heldout_mse"]
    assert set(mse) == {str(s) for s in result.BLUR_SHARES}
    assert min(mse.values()) == mse[str(made_with)] and max(mse.values()) > 0
    # "none": voxel_average alone, no views judged
    monkeypatch.setattr(t.cfg.protocol, "field_blur", "none")
    share, rec = result.field_share(t)
    assert share == 0.5 and rec["added"] == 0.0 and "heldout_mse" not in rec


def test_the_result_uses_the_chosen_share(tiny_case):
    """field_blur="heldout": vol_pred of an unrefined run is the voxelisation of the field
    blurred by the share field_share chose (recorded in metrics.json); without held-out
    views nothing is added and the record says why; an unknown field_blur is a one-line
    error."""
    from mi_grg.core.voxel_average import convolve_gaussians, voxel_variance
    from mi_grg.training import result
    from mi_grg.training.config import ConfigError, make_config
    from mi_grg.training.trainer import Trainer
    for every in (3, 0):
        t = Trainer(tiny_case, make_config("gr", iterations=150, n_points=200,
                                           eval_every=100, holdout_every=every,
                                           refine="none", field_blur="heldout"),
                    progress=False)
        t.run()
        vol, g, info = result.finish(t, progress=False)
        rec = info["voxel_average"]
        assert rec["share"] == rec["voxel_average"] + rec["added"]
        ref = voxelize(convolve_gaussians(t.field_gaussians(), rec["share"] * voxel_variance(
            tiny_case.geometry, 1.0)), tiny_case.geometry, extent=t.extent)
        np.testing.assert_allclose(vol, ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())
        assert ("skipped" in rec) == (every == 0)
        if every == 0:
            assert "holdout_every=0" in rec["skipped"] and rec["added"] == 0.0
    with pytest.raises(ConfigError, match="field_blur must be one of heldout, none"):
        make_config("gr", field_blur="auto")
