"""The projector's input checks: shapes, finite values, valid Gaussians and its error type."""
from __future__ import annotations

import drjit as dr

from mi_grg.core.gaussians import Gaussians, first_failure, gaussian_checks


class ProjectorError(ValueError):
    """Invalid projector input; the message names the argument."""


def check_finite(name, arr, shape_txt):
    ok = dr.all(dr.isfinite(arr), axis=None) if dr.width(arr) else True
    if not bool(ok):
        raise ProjectorError(f"{name} {shape_txt} contains NaN or Inf")


def validate(g: Gaussians, n: int, density_scale, means2d, n_views: int):
    for name, arr, k in (("positions", g.positions, 3), ("scales", g.scales, 3),
                         ("rotations", g.rotations, 4)):
        if len(arr) != k:
            raise ProjectorError(f"gaussians.{name} must have {k} components, got {len(arr)}")
        for comp in arr:
            if dr.width(comp) != n:
                raise ProjectorError(f"gaussians.{name} has {dr.width(comp)} entries, densities has {n}")
    if density_scale is not None and dr.width(density_scale) != n:
        raise ProjectorError(f"density_scale must have shape [N] = [{n}], got {dr.width(density_scale)}")
    msg = first_failure(g, gaussian_checks(g, density_scale))
    if msg is not None:
        raise ProjectorError(msg)
    if means2d is not None:
        if len(means2d) != 2 or dr.width(means2d) != n * n_views:
            raise ProjectorError(f"means2d must be a Vector2f of N * views = {n * n_views} entries "
                                 f"(view-major: index = view * N + gaussian), got {dr.width(means2d)}")
        check_finite("means2d", dr.detach(means2d), "[views * N, 2]")

