"""Gaussians activations (mi_grg.core.gaussians): softplus density and its inverse vs float64."""
import numpy as np

import mi_grg  # noqa: F401
import mitsuba as mi

from mi_grg.core.gaussians import Gaussians


def test_density_activation_round_trip_against_float64(variant):
    """to_raw is log(expm1(d)) (float64 reference) to float32 accuracy over 1e-8 .. 50,
    including the 1e-3 .. 0.1 range of trained densities where 1 - exp(-d) cancels, and
    from_raw(to_raw(d)) returns d."""
    d = np.logspace(-8, np.log10(50.0), 400).astype(np.float32)
    n = d.size
    g = Gaussians.from_numpy(np.zeros((n, 3)), np.full((n, 3), 0.1), None, d)
    raw = np.asarray(g.to_raw()["raw_densities"], np.float64)
    want = np.log(np.expm1(d.astype(np.float64)))
    np.testing.assert_allclose(raw, want, rtol=2e-6, atol=2e-6)
    back = np.asarray(Gaussians.from_raw(g.to_raw()).densities, np.float64)
    np.testing.assert_allclose(back, d, rtol=2e-6)
    assert isinstance(g.to_raw()["raw_densities"], mi.Float)
