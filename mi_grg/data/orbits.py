"""Non-circular scans built from a circular ``Geometry``: a wobbling orbit and a half-fan
(offset-detector) scan, as per-view vectors (``mi_grg.core.view_vectors``)."""
from __future__ import annotations

import numpy as np

from mi_grg.core.geometry import Geometry

__all__ = ["wobbling", "half_fan"]


def _rotate(x, axis, angle):
    """Rodrigues rotation of rows ``x`` [k, 3] about unit ``axis`` [k, 3] by ``angle`` [k]."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return x * c + np.cross(axis, x) * s + axis * np.sum(axis * x, 1, keepdims=True) * (1 - c)


def wobbling(geometry: Geometry, height=0.12, roll_deg=2.0, dsd=0.03, cycles=3,
             skew_deg=0.0) -> Geometry:
    """``geometry``'s views with a per-view wobble: source (and detector) height
    ``height`` x sin (the detector stays), detector roll ``roll_deg`` x cos (about the detector normal) and
    source-detector distance (1 + ``dsd`` sin) x DSD, each varying ``cycles`` times (phases
    apart) over the scan; the detector keeps its place and pixel steps. ``skew_deg``
    turns the row step v (alone) within the detector plane by ``skew_deg`` x sin: the
    pixel grid is then a parallelogram (columns no longer at right angles to rows).
    Lengths in the scan's unit."""
    a = geometry.angles
    t = 2 * np.pi * cycles * (a - a.min()) / max(np.ptp(a), 1e-12) if a.size > 1 else a * 0
    base = geometry.circular().view_vectors()
    s, d, U, V = base[:, 0:3], base[:, 3:6], base[:, 6:9], base[:, 9:12]
    up = np.array([0.0, 0.0, 1.0])
    dz = height * np.sin(t)
    roll = np.radians(roll_deg) * np.cos(t + 1.0)
    n = np.cross(V, U)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    U, V = _rotate(U, n, roll), _rotate(V, n, roll + np.radians(skew_deg) * np.sin(t + 0.5))
    if geometry.mode == "cone":
        # source moves along the source-axis line so that DSD changes by dsd x DSD
        s = s * (1 + dsd * geometry.DSD / geometry.DSO * np.sin(t + 2.0))[:, None]
        s = s + dz[:, None] * up
    return geometry.replace(vectors=np.concatenate([s, d, U, V], 1), vector_angles=None)


def half_fan(geometry: Geometry, fraction=0.3) -> Geometry:
    """The circular scan with its detector offset by ``fraction`` of its width along e_u."""
    off = (geometry.offDetector[0], geometry.offDetector[1] + fraction * geometry.sDetector[1])
    return geometry.replace(offDetector=off)
