"""mi_grg.operator: one shape (A(x), A.T(y)) over both forward models. References: the
adjoint dot-product test in float64, and the projectors' own calls (the operator adds no
arithmetic of its own)."""
import numpy as np
import pytest

import mi_grg
import mitsuba as mi
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.core.gaussians import Gaussians
from mi_grg.core.joseph import back_project, forward_project
from mi_grg.core.projector import project, project_dr


def _geometry(views=4):
    return Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(12, 14), sDetector=(3.0, 4.0),
                    nVoxel=(8, 9, 10), sVoxel=(2.0, 2.2, 2.4), offOrigin=(0.1, -0.05, 0.02),
                    angles=circular_angles(views) + 0.3)


def _gaussians(rng, n=5):
    return Gaussians.from_numpy(positions=rng.uniform(-0.5, 0.5, (n, 3)),
                                scales=rng.uniform(0.1, 0.3, (n, 3)),
                                rotations=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
                                densities=rng.uniform(0.5, 1.5, n))


def test_voxel_operator_is_the_joseph_projector_and_its_adjoint_passes_the_dot_test():
    rng = np.random.default_rng(3)
    geo = _geometry()
    A = mi_grg.operator(geo, kind="voxels")
    x = rng.random(geo.nVoxel).astype(np.float32)
    y = rng.random(A.range_shape).astype(np.float32)
    Ax, Aty = A(x), A.T(y)
    assert Ax.shape == A.range_shape and Aty.shape == A.domain_shape == tuple(geo.nVoxel)
    np.testing.assert_array_equal(Ax, forward_project(x, geo))
    # the adjoint scatter-adds in thread order: two calls agree to float32 rounding
    np.testing.assert_allclose(Aty, back_project(y, geo), rtol=1e-6, atol=1e-6)
    lhs = float(np.dot(Ax.ravel().astype(np.float64), y.ravel()))
    rhs = float(np.dot(x.ravel().astype(np.float64), Aty.ravel()))
    assert lhs == pytest.approx(rhs, rel=1e-5)
    assert A.T.T is A
    # a Dr.Jit tensor in, a Dr.Jit tensor out, with the same values
    t = A(mi.TensorXf(x))
    assert isinstance(t, mi.TensorXf)
    np.testing.assert_array_equal(np.asarray(t.numpy()), Ax)


def test_operator_angles_select_views():
    rng = np.random.default_rng(4)
    geo = _geometry(views=6)
    x = rng.random(geo.nVoxel).astype(np.float32)
    A = mi_grg.operator(geo, kind="voxels", angles=geo.angles[[1, 4]])
    np.testing.assert_array_equal(A(x), forward_project(x, geo)[[1, 4]])


def _same_to_rounding(actual, desired):
    desired = np.asarray(desired, np.float32)
    np.testing.assert_allclose(np.asarray(actual, np.float32), desired, rtol=1e-6,
                               atol=1e-6 * float(np.abs(desired).max()))


def test_gaussian_operator_is_project_dr_and_has_no_adjoint():
    rng = np.random.default_rng(5)
    geo = _geometry()
    g = _gaussians(rng)
    scale = mi.Float(rng.uniform(1.0, 2.0, 5).astype(np.float32))
    A = mi_grg.operator(geo, kind="gaussians", extent=3.0, density_scale=scale)
    out = A(g)
    assert isinstance(out, mi.TensorXf) and tuple(out.shape) == A.range_shape
    # the same kernel; its scatter-adds sum in thread order, so equal to float32 rounding
    _same_to_rounding(out.numpy(), project_dr(g, geo, extent=3.0, density_scale=scale).numpy())
    plain = mi_grg.operator(geo, kind="gaussians")(g)
    _same_to_rounding(plain.numpy(), project(g, geo))
    assert A.domain_shape is None
    with pytest.raises(ValueError, match="no adjoint"):
        A.T


def test_bad_operator_arguments_are_one_line_errors():
    with pytest.raises(ValueError, match="kind must be one of gaussians, voxels"):
        mi_grg.operator(_geometry(), kind="rays")
    with pytest.raises(ValueError, match="geometry must be a mi_grg.Geometry"):
        mi_grg.operator("scan.xml")
