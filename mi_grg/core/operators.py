"""One shape for both forward models: ``A = mi_grg.operator(geometry, kind=...)``,
``A(x)`` the projections [view, v, u] of ``x``, ``A.T(y)`` the adjoint where one exists
(tomosipo's shape; a thin layer over the projectors, which stay the reference).

    kind="voxels":    x a volume [x, y, z] -> the Joseph projector (``core.joseph``);
                      ``A.T`` its exact adjoint, a volume [x, y, z].
    kind="gaussians": x a ``Gaussians`` -> the closed-form line integrals
                      (``core.projector.project_dr``); no ``A.T``: its domain is the
                      Gaussians' parameters, not a vector space the projections map back
                      to (``dr.backward`` through ``A(x)`` gives their gradients).

NumPy in, NumPy out (float32); a Dr.Jit tensor (voxels) or Gaussians in, a differentiable
``mi.TensorXf`` out.
"""
from __future__ import annotations

import numpy as np

from mi_grg.core.geometry import Geometry

KINDS = ("gaussians", "voxels")


class Operator:
    """The forward model of ``geometry`` (``angles`` override its angles; gaussians:
    ``extent`` and ``density_scale`` as ``project_dr`` takes them)."""

    def __init__(self, geometry: Geometry, kind: str = "voxels", angles=None, extent=None,
                 density_scale=None):
        if not isinstance(geometry, Geometry):
            raise ValueError(f"geometry must be a mi_grg.Geometry, got {type(geometry).__name__}")
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
        self.geometry = geometry if angles is None else geometry.with_angles(angles)
        self.kind, self.extent, self.density_scale = kind, extent, density_scale

    @property
    def range_shape(self) -> tuple:
        """The projections' shape [view, v, u]."""
        return (self.geometry.n_views, *(int(n) for n in self.geometry.nDetector))

    @property
    def domain_shape(self) -> tuple | None:
        """The volume's shape [x, y, z] (voxels); None for Gaussians."""
        return tuple(int(n) for n in self.geometry.nVoxel) if self.kind == "voxels" else None

    def __call__(self, x):
        geo = self.geometry
        if self.kind == "gaussians":
            from mi_grg.core.projector import project_dr
            return project_dr(x, geo, extent=self.extent, density_scale=self.density_scale)
        from mi_grg.core.joseph import forward_project, forward_project_dr
        return (forward_project(x, geo) if isinstance(x, np.ndarray)
                else forward_project_dr(x, geo))

    @property
    def T(self) -> "Adjoint":
        """The adjoint A^T (voxels only)."""
        if self.kind != "voxels":
            raise ValueError("the Gaussian projector has no adjoint operator: its input is "
                             "the Gaussians' parameters (use dr.backward through A(x) for "
                             "their gradients)")
        return Adjoint(self)


class Adjoint:
    """A^T of a voxel ``Operator``: projections [view, v, u] -> a volume [x, y, z]."""

    def __init__(self, forward: Operator):
        self.forward = forward

    def __call__(self, y):
        from mi_grg.core.joseph import back_project, back_project_dr
        geo = self.forward.geometry
        return back_project(y, geo) if isinstance(y, np.ndarray) else back_project_dr(y, geo)

    @property
    def T(self) -> Operator:
        return self.forward


def operator(geometry: Geometry, kind: str = "voxels", **options) -> Operator:
    """``Operator(geometry, kind, **options)``: see the module docstring."""
    return Operator(geometry, kind, **options)
