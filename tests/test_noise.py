"""TIGRE-style CT noise: photon statistics vs the model, normalisation, guards, settings."""
import math

import numpy as np
import pytest

import mi_grg  # noqa: F401
from mi_grg.data.noise import NoiseModel


@pytest.mark.parametrize("I0,std", [(1e4, 10.0), (200.0, 5.0), (1e3, 0.0)])
def test_count_statistics_match_poisson_plus_gaussian(I0, std):
    # Two constant levels over many pixels; the larger one is the stack's maximum m, so
    # the model expects mean counts I0 exp(-p / m) and variance mean + std^2.
    m, low, n = 2.5, 0.8, 200_000
    proj = np.concatenate([np.full(n, m), np.full(n, low)]).reshape(2, 400, 500)
    model = NoiseModel(I0=I0, electronic_std=std, clip_negative=False)
    noisy = model.apply(proj, np.random.default_rng(11))
    assert noisy.dtype == np.float32 and noisy.shape == proj.shape
    counts = I0 * np.exp(-noisy.astype(np.float64).reshape(2, -1) / m)
    for level, c in zip((m, low), counts):
        mean = I0 * math.exp(-level / m)
        var = mean + std ** 2
        se_mean = math.sqrt(var / n)
        se_var = var * math.sqrt(2.0 / n)
        assert abs(c.mean() - mean) < 4 * se_mean, (c.mean(), mean, se_mean)
        assert abs(c.var() - var) < 4 * se_var, (c.var(), var, se_var)


def test_normalisation_by_the_maximum():
    # p / max(p) enters the model: scaling the input scales the output, same draws.
    proj = np.random.default_rng(0).uniform(0.0, 1.0, (3, 20, 30))
    model = NoiseModel()
    a = model.apply(proj, np.random.default_rng(5))
    b = model.apply(7.0 * proj, np.random.default_rng(5))
    np.testing.assert_allclose(b, 7.0 * a, rtol=1e-5, atol=1e-6)
    # ... and the most attenuated ray sees I0 / e photons on average whatever the units.
    big = np.full((1, 300, 300), 40.0)
    big[0, 0, 0] = 40.0
    counts = 1e4 * np.exp(-model.apply(big, np.random.default_rng(1)).astype(np.float64) / 40.0)
    assert abs(counts.mean() - 1e4 / math.e) < 4 * math.sqrt((1e4 / math.e + 100) / 90_000)


def test_rng_reproducibility():
    proj = np.random.default_rng(0).uniform(0, 2, (2, 16, 16))
    m = NoiseModel()
    a = m.apply(proj, np.random.default_rng(3))
    b = m.apply(proj, np.random.default_rng(3))
    c = m.apply(proj, np.random.default_rng(4))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.abs(a - proj).max() > 0     # noise was added


def test_negative_clip_and_log_floor():
    # Unattenuated pixels: counts around I0, about half above it -> negative line integrals.
    proj = np.zeros((1, 100, 100))
    proj[0, 0, 0] = 1.0
    raw = NoiseModel(clip_negative=False).apply(proj, np.random.default_rng(0))
    clipped = NoiseModel().apply(proj, np.random.default_rng(0))
    assert (raw < 0).mean() > 0.3
    assert clipped.min() == 0.0 and np.array_equal(clipped, np.maximum(raw, 0))
    # Few photons and strong electronic noise: counts <= 0 are floored at 1 photon.
    p = np.full((1, 50, 50), 3.0)
    low = NoiseModel(I0=2.0, electronic_std=10.0, clip_negative=False).apply(
        p, np.random.default_rng(0))
    assert np.all(np.isfinite(low))
    assert np.isclose(low.max(), 3.0 * math.log(2.0), rtol=1e-6)   # -log(1 / I0) * max
    # Nothing attenuates at all: normalised by 1 instead of dividing by zero.
    zero = NoiseModel().apply(np.zeros((1, 8, 8)), np.random.default_rng(0))
    assert np.all(np.isfinite(zero)) and zero.min() >= 0


@pytest.mark.parametrize("kw", [dict(I0=0), dict(I0=-5), dict(I0=float("nan")),
                                dict(I0=float("inf")), dict(I0="a"), dict(I0=True),
                                dict(electronic_std=-1), dict(electronic_std=float("nan")),
                                dict(clip_negative="yes")])
def test_invalid_parameters(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        NoiseModel(**kw)


def test_invalid_inputs():
    m = NoiseModel()
    with pytest.raises(ValueError, match="finite"):
        m.apply(np.array([[[0.0, np.nan]]]), np.random.default_rng(0))
    with pytest.raises(TypeError, match="Generator"):
        m.apply(np.zeros((1, 2, 2)), 3)


def test_dict_round_trip():
    m = NoiseModel(I0=5e3, electronic_std=2.5, clip_negative=False)
    d = m.to_dict()
    assert d == {"I0": 5e3, "electronic_std": 2.5, "clip_negative": False}
    assert NoiseModel.from_dict(d) == m
    assert NoiseModel.from_dict({}) == NoiseModel()
    with pytest.raises(ValueError, match="photons"):
        NoiseModel.from_dict({"I0": 1e4, "photons": 3, "std": 1})
    with pytest.raises(ValueError, match="I0"):
        NoiseModel.from_dict({"I0": -1})
