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
    # The round trip passes through a float32 raw value: an error of one of its ulps,
    # eps |raw|, is a relative error eps |raw| of d (d ~ exp(raw) for small d; raw is
    # -18 at 1e-8, so 2e-6 per ulp).
    eps = np.finfo(np.float32).eps
    bound = 4 * eps * (1 + np.abs(want))
    rel = np.abs(back - d) / d
    assert np.all(rel <= bound), (d[rel > bound], rel[rel > bound], bound[rel > bound])
    assert np.median(rel) < 4 * eps     # no bias: 1.1 ulps on the CPU, 2.2 on an H100
    assert isinstance(g.to_raw()["raw_densities"], mi.Float)


def test_softplus_and_its_derivative_against_float64(variant):
    """from_raw's density is softplus(x) to a few float32 ulps over x in [-30, 30] (no
    log(1 + t) rounding, which cost 4e-6 relative at densities ~ 0.05 with CUDA's log),
    and its derivative is the logistic function, also at x = 0 (1/2, not 0)."""
    import drjit as dr
    eps = np.finfo(np.float32).eps
    x = np.concatenate([np.linspace(-30, 30, 6001), [0.0, -2.946, 1e-7, -1e-7]]).astype(np.float32)
    xr = mi.Float(x)
    dr.enable_grad(xr)
    raw = {"positions": mi.Point3f(0, 0, 0), "raw_scales": mi.Vector3f(0, 0, 0),
           "raw_rotations": mi.Vector4f(1, 0, 0, 0), "raw_densities": xr}
    d = Gaussians.from_raw(raw).densities
    dr.backward(dr.sum(d))
    x64 = x.astype(np.float64)
    want, slope = np.logaddexp(0.0, x64), 1.0 / (1.0 + np.exp(-x64))
    # exp's argument carries eps |x| of relative error into exp(-|x|): the (1 + |x|) factor
    bound = 4 * eps * (1 + np.abs(x64))
    rel = np.abs(np.asarray(d, np.float64) - want) / want
    assert np.all(rel <= bound), (x[rel > bound], rel[rel > bound])
    g = np.asarray(dr.grad(xr), np.float64)
    rel = np.abs(g - slope) / slope
    assert np.all(rel <= bound), (x[rel > bound], g[rel > bound], slope[rel > bound])
    assert abs(g[x == 0][0] - 0.5) <= 4 * eps   # dr.maximum and dr.abs gave 0 there
