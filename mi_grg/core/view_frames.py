"""Per-view detector frames, read off the one ray formula (``Geometry.vector_rays`` of each
view's vectors) so that the projector follows it."""
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
    ``origin + h e_n + (a_u + u du + v sk) e_u + (a_v + v dv) e_v`` where ``origin`` is the
    source (cone) or the corner pixel's point (parallel, a_u = a_v = 0); parallel rays run
    along e_n. (e_n, e_u, e_v) is orthonormal: a skewed detector (row step not orthogonal
    to the column step) has the row step's e_u component in ``sk``, 0 on a rectangular
    pixel grid. Arrays are [view, 3]; the detector values h, a_u, a_v, du, dv, sk are floats
    shared by all views (``shared``: every circular scan) or float64 arrays [view] (a
    per-view scan whose views differ). ``skewed`` is whether any view of the scan the
    frames were read from has sk != 0 (kept by ``select``: the projector's kernels then
    carry the shear)."""
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
    sk: float = 0.0
    skewed: bool = False

    @property
    def shared(self) -> bool:
        return isinstance(self.h, float)

    def _values(self) -> tuple:
        return (self.h, self.a_u, self.a_v, self.du, self.dv, self.sk)

    def detector_values(self, view: int) -> tuple:
        """(h, a_u, a_v, du, dv, sk) of one view."""
        if self.shared:
            return self._values()
        return tuple(float(x[view]) for x in self._values())

    def select(self, views) -> "ViewFrames":
        """The frames of the views ``views`` (a slice or index array)."""
        pick = lambda x: x if isinstance(x, float) else np.asarray(x)[views]  # noqa: E731
        return ViewFrames(self.cone, self.e_n[views], self.e_u[views], self.e_v[views],
                          self.origin[views], *(pick(x) for x in self._values()),
                          skewed=self.skewed)

    def groups(self) -> list:
        """Runs [(start, stop)] of consecutive views with equal detector values (one run
        for a shared frame): the projector launches one set of kernels per run."""
        if self.shared:
            return [(0, self.e_n.shape[0])]
        vals = np.stack(self._values(), 1)
        cut = np.nonzero(np.any(vals[1:] != vals[:-1], axis=1))[0] + 1
        edges = [0, *cut.tolist(), vals.shape[0]]
        return list(zip(edges[:-1], edges[1:]))


def view_frames(geometry: Geometry, angles=None) -> ViewFrames:
    """The detector frame of every view, read off the ray formula (float64), so that the
    projector follows the one ray formula of mi_grg. Raises if the rays are not those of
    a planar detector. Detector values equal to 1e-9 in every view are shared (floats);
    a row step orthogonal to the column step to 1e-9 has sk = 0 exactly."""
    vec = geometry.view_vectors(angles)
    comps = [vec[:, k] for k in range(12)]
    a = vec[:, 0]
    nv, nu = geometry.nDetector

    def at(v, u):
        o, d, length = geometry.vector_rays(comps, np.full_like(a, float(v)),
                                            np.full_like(a, float(u)))
        o = np.stack(np.broadcast_arrays(*o), -1)
        d = np.stack(np.broadcast_arrays(*d), -1)
        return o, d, o + np.asarray(length)[..., None] * d

    o00, d00, q00 = at(0, 0)
    o01, _, q01 = at(0, 1)
    o10, _, q10 = at(1, 0)
    _, _, qff = at(nv, nu)
    E_u, E_v = q01 - q00, q10 - q00
    du = np.linalg.norm(E_u, axis=1)
    e_u = E_u / du[:, None]
    scale = float(np.abs(q00).max() + 1.0)
    if not np.allclose(qff, q00 + nu * E_u + nv * E_v, rtol=0, atol=1e-9 * scale):
        raise ProjectorError("geometry.rays is not affine in the pixel coordinates "
                             "(planar detector expected)")
    # a skewed detector: the row step's part along e_u is a shear of the pixel lattice
    sk = np.sum(E_v * e_u, 1)
    sk = np.where(np.abs(sk) > 1e-9 * np.linalg.norm(E_v, axis=1), sk, 0.0)
    skewed = bool(np.any(sk != 0))
    if skewed:
        E_v = E_v - sk[:, None] * e_u
    dv = np.linalg.norm(E_v, axis=1)
    e_v = E_v / dv[:, None]
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
        tilt = np.abs(np.sum(e_n * e_u, 1)) + np.abs(np.sum(e_n * e_v, 1))
        if tilt.max() > 1e-9:
            raise ProjectorError(f"view {int(np.argmax(tilt))}: parallel-beam direction is not "
                                 "normal to the detector")
        origin = q00
        h = np.full_like(a, float(geometry.DSD))
        a_u = a_v = np.zeros_like(a)
    vals = (h, a_u, a_v, du, dv, sk)
    if all(np.ptp(x) <= 1e-9 * (np.abs(x).max() + scale) for x in vals):
        return ViewFrames(cone, e_n, e_u, e_v, origin, *(float(x[0]) for x in vals),
                          skewed=skewed)
    return ViewFrames(cone, e_n, e_u, e_v, origin, *(np.asarray(x, np.float64) for x in vals),
                      skewed=skewed)

