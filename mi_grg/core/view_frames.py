"""Per-view detector frames, read off ``Geometry.rays`` so that the projector follows mi_grg's
one ray formula."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_grg.core.geometry import Geometry
from mi_grg.core.projector_inputs import ProjectorError

__all__ = ["ViewFrames", "view_frames"]


@dataclass(frozen=True)
class ViewFrames:
    """Per-view detector frames derived (in float64) from ``Geometry.rays``.

    Pixel (v, u) (continuous, centre of pixel (i, j) at (i + 0.5, j + 0.5)) lies at
    ``origin + h e_n + (a_u + u du) e_u + (a_v + v dv) e_v`` where ``origin`` is the source
    (cone) or the corner pixel's point (parallel, a_u = a_v = 0); parallel rays run along
    e_n. Arrays are [view, 3]; scalars are shared by all views."""
    cone: bool
    e_n: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    origin: np.ndarray
    h: float
    a_u: float
    a_v: float
    du: float
    dv: float


def view_frames(geometry: Geometry, angles=None) -> ViewFrames:
    """The detector frame of every view, read off ``geometry.rays`` (float64), so that the
    projector follows the one ray formula of mi_grg. Raises if the rays are not those of
    a planar detector with orthogonal axes and view-independent offsets."""
    a = geometry.angles if angles is None else np.asarray(angles, np.float64).reshape(-1)
    c, s = np.cos(a), np.sin(a)
    nv, nu = geometry.nDetector

    def at(v, u):
        o, d, length = geometry.rays(c, s, np.full_like(a, float(v)), np.full_like(a, float(u)))
        o = np.stack(np.broadcast_arrays(*o), -1)
        d = np.stack(np.broadcast_arrays(*d), -1)
        return o, d, o + np.asarray(length)[..., None] * d

    o00, d00, q00 = at(0, 0)
    o01, _, q01 = at(0, 1)
    o10, _, q10 = at(1, 0)
    _, _, qff = at(nv, nu)
    E_u, E_v = q01 - q00, q10 - q00
    du, dv = np.linalg.norm(E_u, axis=1), np.linalg.norm(E_v, axis=1)
    e_u, e_v = E_u / du[:, None], E_v / dv[:, None]
    scale = float(np.abs(q00).max() + 1.0)
    if not np.allclose(qff, q00 + nu * E_u + nv * E_v, rtol=0, atol=1e-9 * scale):
        raise ProjectorError("geometry.rays is not affine in the pixel coordinates "
                             "(planar detector expected)")
    if np.abs(np.sum(e_u * e_v, 1)).max() > 1e-9:
        raise ProjectorError("detector axes e_u, e_v are not orthogonal")
    cone = geometry.mode == "cone"
    if cone:
        if not (np.allclose(o00, o01, atol=1e-12 * scale) and np.allclose(o00, o10, atol=1e-12 * scale)):
            raise ProjectorError("cone-beam rays do not share one source point")
        origin = o00
        e_n = np.cross(e_u, e_v)
        rel = q00 - origin
        e_n *= np.sign(np.sum(rel * e_n, 1))[:, None]
        h = np.sum(rel * e_n, 1)
        a_u, a_v = np.sum(rel * e_u, 1), np.sum(rel * e_v, 1)
    else:
        e_n = d00
        if np.abs(np.sum(e_n * e_u, 1)).max() > 1e-9 or np.abs(np.sum(e_n * e_v, 1)).max() > 1e-9:
            raise ProjectorError("parallel-beam direction is not normal to the detector")
        origin = q00
        h = np.full_like(a, float(geometry.DSD))
        a_u = a_v = np.zeros_like(a)
    for name, arr in (("h", h), ("a_u", a_u), ("a_v", a_v), ("du", du), ("dv", dv)):
        if np.ptp(arr) > 1e-9 * (np.abs(arr).max() + scale):
            raise ProjectorError(f"detector frame value {name} differs between views")
    return ViewFrames(cone, e_n, e_u, e_v, origin, float(h[0]), float(a_u[0]), float(a_v[0]),
                      float(du[0]), float(dv[0]))

