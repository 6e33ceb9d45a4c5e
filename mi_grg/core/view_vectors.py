"""Per-view scan geometry as ASTRA-style vectors: the one ray formula of mi_grg.

A view is 12 numbers (ASTRA's ``cone_vec`` order; ``parallel3d_vec`` for parallel beam):

    (s_x, s_y, s_z,  d_x, d_y, d_z,  u_x, u_y, u_z,  v_x, v_y, v_z)

``s`` is the source (cone beam) or the ray direction, source towards detector (parallel
beam); ``d`` the detector centre; ``u`` and ``v`` the steps from one pixel to the next
along a row (column index) and down a column (row index). Pixel (i, j) (row i, column j)
is centred at ``d + (j + 0.5 - nU/2) u + (i + 0.5 - nV/2) v``. A circular ``Geometry``
converts to this form exactly (``circular_vectors``); ``rays`` is the formula every
projector, reference and sensor evaluates (NumPy float64 or Dr.Jit float32 alike).
"""
from __future__ import annotations

import numpy as np

__all__ = ["VectorError", "check_vectors", "circular_vectors", "rays", "sees_volume"]


class VectorError(ValueError):
    """A per-view vector that cannot describe a view; the message names the view."""


def _sqrt(x):
    if isinstance(x, np.ndarray) or np.isscalar(x):
        return np.sqrt(x)
    import drjit as dr
    return dr.sqrt(x)


def circular_vectors(cos_a, sin_a, DSD, DSO, dDetector, offDetector, mode="cone"):
    """The 12 components of the circular scan's views (``docs/conventions.md``): source
    ``DSO n``, detector centre ``-(DSD - DSO) n + offDetector[0] e_v + offDetector[1] e_u``,
    ``u = du e_u``, ``v = dv e_v`` with ``n = (cos a, sin a, 0)``, ``e_u = (-sin a, cos a,
    0)``, ``e_v = (0, 0, -1)``; parallel beam: the ray ``-n`` first. Works on NumPy arrays
    and Dr.Jit arrays (one entry per view or per ray)."""
    dv, du = dDetector
    back = DSD - DSO
    zero = 0.0 * cos_a
    dx = -back * cos_a - offDetector[1] * sin_a
    dy = -back * sin_a + offDetector[1] * cos_a
    dz = zero - offDetector[0]
    if mode == "cone":
        s = (DSO * cos_a, DSO * sin_a, zero)
    else:
        s = (-cos_a, -sin_a, zero)
    return (*s, dx, dy, dz, -du * sin_a, du * cos_a, zero, zero, zero, zero - dv)


def rays(vec, v, u, nDetector, mode, DSD):
    """Rays through continuous detector positions; the single place of the ray formula.

    Args:
        vec: the 12 components (each a scalar or an array per ray).
        v, u: detector coordinates in pixels; pixel (i, j) has its centre at
            (v, u) = (i + 0.5, j + 0.5).
        nDetector: (nV, nU); mode: "cone" or "parallel"; DSD: parallel-beam rays start
            ``DSD`` before the detector.
    Returns:
        (origin, direction, length): (x, y, z) component tuples; unit direction; the
        distance from origin to the detector position.
    """
    nv, nu = nDetector
    su, sv = u - 0.5 * nu, v - 0.5 * nv
    px = vec[3] + su * vec[6] + sv * vec[9]
    py = vec[4] + su * vec[7] + sv * vec[10]
    pz = vec[5] + su * vec[8] + sv * vec[11]
    if mode == "cone":
        ox, oy, oz = vec[0], vec[1], vec[2]
        dx, dy, dz = px - ox, py - oy, pz - oz
        length = _sqrt(dx * dx + dy * dy + dz * dz)
        inv = 1.0 / length
        return (ox + 0.0 * px, oy + 0.0 * py, oz + 0.0 * pz), (dx * inv, dy * inv, dz * inv), length
    inv = 1.0 / _sqrt(vec[0] * vec[0] + vec[1] * vec[1] + vec[2] * vec[2])
    dx, dy, dz = vec[0] * inv, vec[1] * inv, vec[2] * inv
    ox, oy, oz = px - DSD * dx, py - DSD * dy, pz - DSD * dz
    return (ox, oy, oz), (dx + 0.0 * px, dy + 0.0 * py, dz + 0.0 * pz), DSD + 0.0 * px


def _detector_coords(points, s, d, U, V, mode):
    """Continuous (u, v) offsets (in pixels, from the centre) where the rays through
    ``points`` [k, 3] meet the detector plane of one view (None: a point behind the source)."""
    n = np.cross(U, V)
    if mode == "cone":
        rel = points - s
        denom = rel @ n
        t = ((d - s) @ n) / np.where(denom == 0, np.inf, denom)
        if np.any(t <= 0):
            return None
        hit = s + t[:, None] * rel
    else:
        t = ((d - points) @ n) / (s @ n)
        hit = points + t[:, None] * s
    G = np.array([[U @ U, U @ V], [U @ V, V @ V]])
    rhs = np.stack([(hit - d) @ U, (hit - d) @ V], 0)
    return np.linalg.solve(G, rhs)


def sees_volume(vec, bbox, nDetector, mode) -> bool:
    """Whether the detector of one view (12 float64 numbers) meets the shadow of the
    volume's box ``bbox`` [[lo], [hi]] (a box reaching behind the source counts as seen)."""
    lo, hi = np.asarray(bbox, np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    vec = np.asarray(vec, np.float64)
    uv = _detector_coords(corners, vec[0:3], vec[3:6], vec[6:9], vec[9:12], mode)
    if uv is None:
        return True
    nv, nu = nDetector
    return bool(uv[0].max() > -nu / 2 and uv[0].min() < nu / 2
                and uv[1].max() > -nv / 2 and uv[1].min() < nv / 2)


def check_vectors(vectors, mode, nDetector, bbox, names=None) -> np.ndarray:
    """``vectors`` as a read-only float64 array [view, 12]; raises ``VectorError`` naming
    the first bad view (``names[i]``, default ``view i``): not 12 finite numbers, zero or
    parallel u and v, a source on the detector plane (parallel beam: a ray along it), a
    detector that does not see the volume."""
    rows = list(vectors) if not isinstance(vectors, np.ndarray) else vectors
    if len(rows) == 0:
        raise VectorError("per-view vectors: none given (one row of 12 numbers per view)")
    out = np.empty((len(rows), 12))
    for i, row in enumerate(rows):
        name = names[i] if names is not None else f"view {i}"
        try:
            r = np.asarray(row, np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise VectorError(f"{name}: vector must be 12 numbers, got {row!r}") from None
        if r.size != 12 or not np.all(np.isfinite(r)):
            raise VectorError(f"{name}: vector must be 12 finite numbers, got {list(np.ravel(row))}")
        s, d, U, V = r[0:3], r[3:6], r[6:9], r[9:12]
        nu_, nv_ = np.linalg.norm(U), np.linalg.norm(V)
        cross = np.linalg.norm(np.cross(U, V))
        if nu_ == 0 or nv_ == 0 or cross <= 1e-9 * nu_ * nv_:
            raise VectorError(f"{name}: detector steps u and v are zero or parallel "
                              f"(u = {list(U)}, v = {list(V)})")
        n = np.cross(U, V) / cross
        if mode == "cone":
            gap = abs((s - d) @ n)
            if gap <= 1e-9 * max(np.linalg.norm(s - d), 1e-300):
                raise VectorError(f"{name}: the source {list(s)} lies on the detector plane")
        elif abs(s @ n) <= 1e-9 * max(np.linalg.norm(s), 1e-300):
            raise VectorError(f"{name}: the ray direction {list(s)} is zero or lies in the "
                              "detector plane")
        if not sees_volume(r, bbox, nDetector, mode):
            raise VectorError(f"{name}: the detector does not see the volume (its shadow "
                              "misses all pixels)")
        out[i] = r
    out.setflags(write=False)
    return out
