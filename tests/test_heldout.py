"""Held-out-view stopping and tuning of the classical methods (mi_grg.protocol.heldout).

References: the held-out split of the trainer (the same function), a scripted method whose
held-out-view error has a known best sweep and setting, and the contract (which views
decided, which views the final run used; bad input names the fix).
"""
import math

import numpy as np
import pytest

import mi_grg  # noqa: F401  (before mitsuba)

from mi_grg.data.case import Case
from mi_grg.protocol.split import holdout_split
from mi_grg.core.geometry import circular_angles
from mi_grg.protocol.heldout import run_heldout, stop_rule
from mi_grg.classical.iterative import reconstruct_asd_pocs, reconstruct_sart
from mi_grg.core.joseph import forward_project


def test_holdout_split():
    fit, held = holdout_split(25, 8)
    assert held.tolist() == [3, 9, 15, 21] and len(fit) == 21
    assert not set(fit) & set(held)
    # Against brute force over every k-subset: the split holds out ceil(n / every) views and
    # its widest gap between fitted neighbours (cyclic, in view steps) is the smallest any
    # choice of that many views can leave; neither end of the arc is held out.
    from itertools import combinations

    def widest_gap(held_set, n):
        fitted = [i for i in range(n) if i not in held_set]
        return max((fitted[(j + 1) % len(fitted)] - fitted[j]) % n or n
                   for j in range(len(fitted)))

    for n in range(4, 15):
        for every in range(2, n):
            fit, held = holdout_split(n, every)
            k = -(-n // every)
            assert len(held) == k and sorted(fit.tolist() + held.tolist()) == list(range(n))
            best = min(widest_gap(set(c), n) for c in combinations(range(n), k))
            assert widest_gap(set(held.tolist()), n) == best, (n, every, held)
            if 2 * k < n:
                assert 0 not in held and n - 1 not in held, (n, every, held)
    fit, held = holdout_split(5, 0)
    assert held.size == 0 and fit.tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="holdout_every"):
        holdout_split(5, -1)


def small_case(views=9, with_gt=True):
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(16, 16),
                          sDetector=(3.0, 3.0), nVoxel=(12, 12, 12), sVoxel=(2.0, 2.0, 2.0),
                          angles=circular_angles(views))
    x = np.zeros(geo.nVoxel, np.float32)
    x[3:9, 4:8, 3:9] = 1.0
    return Case(geometry=geo, train=forward_project(x, geo), vol_gt=x if with_gt else None), x


RAMP = np.linspace(0, 1, 12, dtype=np.float32)[:, None, None] * np.ones((12, 12, 12), np.float32)


def test_rule_picks_the_known_best_sweep_and_setting_then_runs_on_all_views():
    """A scripted method: sweep k returns x_true plus a ramp times |k - peak| (``peak``, a
    setting): the held-out PSNR is infinite (exact projections) at ``peak`` only."""
    case, x_true = small_case()
    calls = []

    def run(proj, geo, n_iter, callback, progress, peak):
        calls.append((proj.shape[0], n_iter, peak))
        for it in range(n_iter):
            k = it + 1
            vol = x_true + 0.2 * abs(k - peak) * RAMP
            if callback(it, vol):
                break
        return vol

    vol, info = run_heldout(case, run, [{"peak": 3}, {"peak": 6}], max_sweeps=30, name="t",
                            project=forward_project, oracle=False, progress=False)
    rule = stop_rule()
    held = holdout_split(9, rule["holdout_every"])[1].tolist()
    assert info["held_out_views"] == held and info["final_views"] == list(range(9))
    # Both peaks give exact projections (scale 1): the tie goes to the first setting.
    assert info["chosen"] == {"setting": {"peak": 3}, "sweeps": 3,
                              "heldout_psnr": info["candidates"][0]["heldout_psnr"]}
    # Each candidate ran until the rule stopped it: patience drops after the peak.
    assert [c["sweeps_run"] for c in info["candidates"]] == [3 + rule["patience"],
                                                              6 + rule["patience"]]
    assert calls[:2] == [(9 - len(held), 30, 3), (9 - len(held), 30, 6)]
    assert calls[2] == (9, 3, 3)                        # final: all views, chosen sweeps
    np.testing.assert_allclose(vol, x_true)


def test_oracle_is_reported_and_decides_nothing():
    case, x_true = small_case()

    def run(proj, geo, n_iter, callback, progress, peak):
        for it in range(n_iter):
            k = it + 1
            # held-out PSNR peaks at ``peak``; the 3-D PSNR would prefer a later sweep
            vol = x_true + 0.2 * abs(k - peak) * RAMP
            vol[0, 0, 0] = 0.05 * max(0, 8 - k)
            if callback(it, vol):
                break
        return vol

    vol, info = run_heldout(case, run, [{"peak": 3}], max_sweeps=30, name="t",
                            project=forward_project, progress=False)
    o = info["oracle"]
    assert info["chosen"]["sweeps"] == 3 and "ground truth" in o["label"]
    assert o["best_sweep"] >= 3 and o["psnr_3d_best"] >= o["psnr_3d_chosen"]
    assert o["gap_db"] == pytest.approx(o["psnr_3d_best"] - o["psnr_3d_chosen"])
    assert vol[0, 0, 0] == pytest.approx(0.25)          # the state of sweep 3, not later


@pytest.mark.parametrize("fn", [reconstruct_sart, reconstruct_asd_pocs])
def test_methods_default_to_the_heldout_rule(fn):
    case, _ = small_case(with_gt=False)
    vol, info = fn(case, n_iter=4, progress=False)
    # (ASD-POCS's TV steps follow the positivity step, so small negatives stay; they grow
    # with the TV weight the one-SE rule chooses, here alpha 0.06)
    assert vol.shape == case.geometry.nVoxel and vol.min() >= -0.02 * vol.max()
    assert info["protocol"] == "heldout" and info["final_views"] == list(range(9))
    assert 1 <= info["chosen"]["sweeps"] <= 4 and "why" in info
    if fn is reconstruct_asd_pocs:
        assert len(info["candidates"]) > 1 and "alpha" in info["chosen"]["setting"]


def test_too_few_views_say_so_and_fall_back_only_when_asked():
    case, _ = small_case(views=1)
    for fn in (reconstruct_sart, reconstruct_asd_pocs):
        with pytest.raises(ValueError, match="stop=none"):
            fn(case, progress=False)
        vol = fn(case, stop="none", n_iter=2, progress=False)
        assert vol.shape == case.geometry.nVoxel
    with pytest.raises(ValueError, match="stop must be one of"):
        reconstruct_sart(case, stop="never")
    with pytest.raises(ValueError, match="apply to stop='heldout' only"):
        reconstruct_sart(case, stop="none", holdout_every=4)
    with pytest.raises(ValueError, match="alpha"):
        reconstruct_asd_pocs(case, stop="none", alpha=[0.002, 0.02])


def noisy_ellipsoids(n=24, sigma=0.05, views=25, seed=1):
    """Ellipsoids at n^3, Joseph projections plus white noise of known std ``sigma``:
    (Case, the noise-free projections)."""
    geo = mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(36, 36),
                          sDetector=(3.0, 3.0), nVoxel=(n, n, n), sVoxel=(2.0, 2.0, 2.0),
                          angles=circular_angles(views))
    g = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    x = (0.5 * ((X / 0.8) ** 2 + (Y / 0.6) ** 2 + (Z / 0.7) ** 2 <= 1)
         + 0.3 * ((X - 0.2) ** 2 + Y ** 2 + Z ** 2 <= 0.09)).astype(np.float32)
    clean = forward_project(x, geo)
    noise = sigma * np.random.default_rng(seed).standard_normal(clean.shape)
    return Case(geometry=geo, train=(clean + noise).astype(np.float32), vol_gt=x), clean


def test_discrepancy_stops_sart_near_its_best_sweep_where_heldout_psnr_cannot():
    """SART on noisy views semi-converges: the held-out PSNR keeps rising past the 3-D
    PSNR's peak (gr's rule alone runs to the cap, far from the oracle); the noise level
    measured on held-out views and the fitted views' residual stop it near the peak."""
    from mi_grg.classical.iterative import sart
    case, clean = noisy_ellipsoids()
    vol, info = reconstruct_sart(case, progress=False)
    held = info["held_out_views"]
    true_noise = float(np.mean((case.train[held].astype(np.float64) - clean[held]) ** 2))
    d = info["discrepancy"]
    assert 0.9 * true_noise <= d["noise_mse"] <= 1.5 * true_noise
    cand = info["candidates"][0]
    first = next(s for s, _, f in cand["residuals"] if f <= d["noise_mse"])
    assert info["chosen"]["sweeps"] == cand["discrepancy_sweep"] == first
    assert info["oracle"]["gap_db"] < 0.5
    # The same case with gr's rule alone (no discrepancy step) lands far from its best.
    _, old = run_heldout(case, lambda p, g, **kw: sart(p, g, **kw), [{}], max_sweeps=20,
                         name="sart", project=forward_project, progress=False)
    assert old["oracle"]["gap_db"] > 2.0
    assert "discrepancy" not in old


def test_widening_doubles_while_the_last_doubling_pays():
    from mi_grg.protocol.widening import Widening
    w = Widening(10, gain_db=0.5, max_factor=8)
    # a value that gains 1 dB per doubling until 40, then 0.1 dB per doubling
    def value(s):
        return math.log2(s) if s <= 40 else math.log2(40) + 0.1 * math.log2(s / 40)
    hist = []
    ends = None
    for s in range(5, 200, 5):
        hist.append((s, value(s)))
        if not w.goes_on(hist, s):
            ends = s
            break
    # doublings at 10, 20, 40 pay (1 dB > 0.5); the one ending at 80 brings 0.1 dB: stop
    assert ends == 80 and not w.binds(hist, ends)
    hist = [(s, math.log2(s)) for s in range(5, 81, 5)]
    assert w.ceiling == 80 and not w.goes_on(hist, 80) and w.binds(hist, 80)
    assert all(w.goes_on(hist[:i + 1], s) for i, (s, _) in enumerate(hist[:-1]))
    for bad in ({"base": 0}, {"base": 5, "gain_db": -1.0}, {"base": 5, "max_factor": 0}):
        with pytest.raises(ValueError):
            Widening(**bad)


def test_a_widening_cap_runs_a_slowly_converging_method_past_its_base(capsys):
    """A scripted method whose held-out error falls as 1 / sweep never stops by the rule:
    with ``widen`` its cap doubles to the ceiling and says so; one whose error is flat
    after sweep 10 stops at the first doubling that brings nothing."""
    from mi_grg.protocol.widening import WIDEN_MAX_FACTOR
    case, x_true = small_case()

    def run(proj, geo, n_iter, callback, progress, flat_from):
        for it in range(n_iter):
            k = min(it + 1, flat_from)
            vol = x_true + (0.5 / k + 1e-3) * RAMP
            if callback(it, vol):
                break
        return vol

    vol, info = run_heldout(case, run, [{"flat_from": 10 ** 6}], max_sweeps=4, name="t",
                            project=forward_project, oracle=False, widen=True,
                            progress=False)
    c = info["candidates"][0]
    assert c["sweeps_run"] == 4 * WIDEN_MAX_FACTOR and c["cap_binds"]
    assert info["cap"]["binds"] and info["chosen"]["sweeps"] == 4 * WIDEN_MAX_FACTOR
    assert "still rose at the widened cap" in capsys.readouterr().err
    vol, info = run_heldout(case, run, [{"flat_from": 10}], max_sweeps=4, name="t",
                            project=forward_project, oracle=False, widen=True,
                            progress=False)
    c = info["candidates"][0]
    # doublings end at 8 and 16 (both gain), at 32 the last 16 sweeps brought nothing
    assert c["sweeps_run"] == 32 and not c["cap_binds"] and not info["cap"]["binds"]
    # without widening the base caps it
    vol, info = run_heldout(case, run, [{"flat_from": 10}], max_sweeps=4, name="t",
                            project=forward_project, oracle=False, progress=False)
    assert info["candidates"][0]["sweeps_run"] == 4 and "cap" not in info


def test_asd_pocs_alpha_rule_bad_values_say_what_to_do():
    case, _ = small_case()
    with pytest.raises(ValueError, match="alpha_rule must be one of"):
        reconstruct_asd_pocs(case, alpha_rule="morozov", progress=False)
    with pytest.raises(ValueError, match="needs stop='heldout'"):
        reconstruct_asd_pocs(case, stop="none", alpha_rule="best", progress=False)
    with pytest.raises(ValueError, match="leaves nothing to choose"):
        reconstruct_asd_pocs(case, alpha=0.02, alpha_rule="best", progress=False)


def test_asd_pocs_best_rule_takes_the_highest_heldout_candidate():
    case, _ = small_case(views=16)
    vol, info = reconstruct_asd_pocs(case, alpha=[0.002, 0.02], alpha_rule="best",
                                     n_iter=4, oracle=False, progress=False)
    best = max(info["candidates"], key=lambda c: c["heldout_psnr"])
    assert info["chosen"]["setting"] == best["setting"]
    assert info["search"]["rule"] == "best held-out PSNR"
