"""The CT scan geometry: one validated type with TIGRE's field names.

Conventions (R2-Gaussian's data reader, so that its published data sets load unchanged;
drawn in ``docs/conventions.md``):

* The source rotates about +z: at angle ``a`` (radians) it sits at
  ``(DSO cos a, DSO sin a, 0)``. The detector centre is at
  ``-(DSD - DSO) (cos a, sin a, 0)`` shifted by ``offDetector``.
* Detector axes: the column index u runs along ``e_u = (-sin a, cos a, 0)``, the row
  index v along ``e_v = (0, 0, -1)``. Pixel (v, u) is centred at
  ``(i + 0.5 - n/2) * dDetector`` along its axis (+ offDetector). Arrays are [v, u].
* Cone beam: the ray of a pixel goes from the source through the pixel centre.
  Parallel beam: it runs along ``-(cos a, sin a, 0)`` through the pixel centre.
* Volumes are stored [x, y, z]; voxel (i, j, k) is centred at
  ``-sVoxel/2 + (index + 0.5) * dVoxel + offOrigin``.
* Projections are stored [view, v, u] as line integrals (-log I/I0) in the units of
  density x length.

All lengths share one unit (that of the data set; R2-Gaussian rescales them on load by
``2 / max(sVoxel)``, see ``Geometry.scaled``).

Per-view scans (``vectors``): each view may instead carry its own source, detector centre
and detector steps (ASTRA's ``cone_vec`` / ``parallel3d_vec`` rows, ``view_vectors``);
``angles`` then stay the nominal angles, and a view's row is found by its angle, so that a
subset of views (``with_angles``) keeps its vectors. The rays of both forms come from
``view_vectors.rays``; a circular scan converts to vectors exactly (``view_vectors()``).
"""
from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass, field

import numpy as np

from mi_grg.core import view_vectors as vv

MODES = ("cone", "parallel")

# Validated per-view rows (by id, while alive) and what they were validated against
_CHECKED = weakref.WeakValueDictionary()
_CHECKED_KEYS: dict = {}


class GeometryError(ValueError):
    """An invalid geometry field; the message names the field."""


def _vector(name, value, length, dtype=float, positive=False):
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise GeometryError(f"{name} must be {length} numbers, got {value!r}") from None
    if arr.shape != (length,):
        raise GeometryError(f"{name} must have {length} entries, got shape {arr.shape} ({value!r})")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise GeometryError(f"{name} must be > 0, got {value!r}")
    if dtype is int:
        if np.any(arr != np.round(arr)):
            raise GeometryError(f"{name} must be integers, got {value!r}")
        return tuple(int(x) for x in arr)
    return tuple(float(x) for x in arr)


@dataclass(frozen=True)
class Geometry:
    """A circular CT scan (TIGRE field names; all lengths in one unit, angles in radians).

    Fields:
        mode:        "cone" or "parallel".
        DSD:         distance source -> detector centre.
        DSO:         distance source -> rotation axis (origin); cone beam needs DSO < DSD.
        nDetector:   detector pixels [v, u] (rows, columns).
        sDetector:   detector size [v, u] (whole detector, not one pixel).
        nVoxel:      volume voxels [x, y, z].
        sVoxel:      volume size [x, y, z] (whole volume, not one voxel).
        offOrigin:   volume centre offset [x, y, z].
        offDetector: detector centre offset [v, u] along (e_v, e_u).
        angles:      projection angles [view], radians (nominal ones for a per-view scan).
        vectors:     None (circular scan) or per-view rows [m, 12] (``view_vectors``
                     order); row r belongs to the view whose angle is ``vector_angles[r]``.
        vector_angles: the nominal angle of each row of ``vectors`` (default: ``angles``).
                     Every angle must have a row; rows of equal angles must be equal.
    """

    mode: str
    DSD: float
    DSO: float
    nDetector: tuple
    sDetector: tuple
    nVoxel: tuple
    sVoxel: tuple
    angles: np.ndarray
    offOrigin: tuple = (0.0, 0.0, 0.0)
    offDetector: tuple = (0.0, 0.0)
    vectors: np.ndarray | None = None
    vector_angles: np.ndarray | None = None

    def __post_init__(self):
        s = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        if self.mode not in MODES:
            raise GeometryError(f"mode must be one of {MODES}, got {self.mode!r}")
        for name in ("DSD", "DSO"):
            v = getattr(self, name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise GeometryError(f"{name} must be a number, got {v!r}") from None
            if not math.isfinite(v) or v <= 0:
                raise GeometryError(f"{name} must be finite and > 0, got {v!r}")
            s(name, v)
        if self.mode == "cone" and self.DSO >= self.DSD:
            raise GeometryError(
                f"DSO (source-origin, {self.DSO}) must be < DSD (source-detector, {self.DSD}) "
                "in cone mode")
        s("nDetector", _vector("nDetector", self.nDetector, 2, int, positive=True))
        s("sDetector", _vector("sDetector", self.sDetector, 2, positive=True))
        s("nVoxel", _vector("nVoxel", self.nVoxel, 3, int, positive=True))
        s("sVoxel", _vector("sVoxel", self.sVoxel, 3, positive=True))
        s("offOrigin", _vector("offOrigin", self.offOrigin, 3))
        s("offDetector", _vector("offDetector", self.offDetector, 2))
        try:
            ang = np.array(self.angles, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise GeometryError(f"angles must be numbers (radians), got {self.angles!r}") from None
        if ang.size == 0:
            raise GeometryError("angles must hold at least one projection angle (radians)")
        if not np.all(np.isfinite(ang)):
            raise GeometryError("angles must be finite (radians)")
        ang.setflags(write=False)
        s("angles", ang)
        if self.mode == "cone":
            # The volume's bounding sphere must stay in front of the source.
            r = 0.5 * float(np.linalg.norm(self.sVoxel)) + float(np.linalg.norm(self.offOrigin))
            if r >= self.DSO:
                raise GeometryError(
                    f"DSO ({self.DSO}) must exceed the volume's bounding radius ({r:.4g}): the "
                    "source would sit inside the volume")
        self._check_vectors(s)

    def _check_vectors(self, s):
        """Validate ``vectors`` and find each view's row (``_rows``)."""
        if self.vectors is None:
            if self.vector_angles is not None:
                raise GeometryError("vector_angles given without vectors")
            s("_rows", None)
            return
        vec = self.vectors
        key = (id(vec), self.mode, self.nDetector, tuple(self.bbox().ravel()))
        if _CHECKED.get(key[0]) is not vec or _CHECKED_KEYS.get(key[0]) != key:
            # a copy of a validated geometry (with_angles, replace) keeps its rows unchecked
            try:
                vec = vv.check_vectors(self.vectors, self.mode, self.nDetector, self.bbox())
            except vv.VectorError as e:
                raise GeometryError(str(e)) from None
            key = (id(vec),) + key[1:]
            _CHECKED[id(vec)] = vec
            _CHECKED_KEYS[id(vec)] = key
            weakref.finalize(vec, _CHECKED_KEYS.pop, id(vec), None)
        va = self.angles if self.vector_angles is None else np.array(
            self.vector_angles, np.float64).reshape(-1)
        if va.shape != (vec.shape[0],):
            raise GeometryError(f"vector_angles has {va.size} entries for {vec.shape[0]} "
                                "vector rows")
        va = np.array(va, np.float64)
        va.setflags(write=False)
        order = np.argsort(va, kind="stable")
        sa = va[order]
        dup = np.nonzero(sa[1:] == sa[:-1])[0]
        for k in dup:
            if not np.array_equal(vec[order[k]], vec[order[k + 1]]):
                raise GeometryError(f"view {order[k + 1]}: its angle {sa[k]!r} is also that of "
                                    f"view {order[k]} with another vector (angles must tell "
                                    "per-view vectors apart)")
        pos = np.minimum(np.searchsorted(sa, self.angles), sa.size - 1)
        bad = np.nonzero(sa[pos] != self.angles)[0]
        if bad.size:
            raise GeometryError(f"view {bad[0]}: angle {self.angles[bad[0]]!r} has no per-view "
                                "vector")
        rows = order[pos]
        rows.setflags(write=False)
        s("vectors", vec)
        s("vector_angles", va)
        s("_rows", rows)

    # ---------------------------------------------------------------- derived values
    @property
    def dDetector(self) -> tuple:
        """Pixel size [v, u]."""
        return tuple(s / n for s, n in zip(self.sDetector, self.nDetector))

    @property
    def dVoxel(self) -> tuple:
        """Voxel size [x, y, z]."""
        return tuple(s / n for s, n in zip(self.sVoxel, self.nVoxel))

    @property
    def n_views(self) -> int:
        return int(self.angles.size)

    @property
    def projection_shape(self) -> tuple:
        """Shape of the projection stack, [view, v, u]."""
        return (self.n_views, *self.nDetector)

    def replace(self, **changes) -> "Geometry":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def with_angles(self, angles) -> "Geometry":
        """The same scan seen at ``angles``; a per-view scan keeps each angle's vector."""
        return self.replace(angles=angles)

    @property
    def per_view(self) -> bool:
        """True where views carry their own vectors (``vectors``)."""
        return self.vectors is not None

    def view_vectors(self, angles=None) -> np.ndarray:
        """Float64 [view, 12] rows (``mi_grg.core.view_vectors`` order) of ``angles``
        (default: the geometry's); a circular scan converts exactly."""
        if angles is not None:
            return self.with_angles(angles).view_vectors()
        if self.per_view:
            return np.array(self.vectors[self._rows])
        a = self.angles
        comps = vv.circular_vectors(np.cos(a), np.sin(a), self.DSD, self.DSO, self.dDetector,
                                    self.offDetector, self.mode)
        return np.stack(np.broadcast_arrays(*comps), -1)

    def as_vectors(self) -> "Geometry":
        """The same scan as a per-view geometry (its rows: ``view_vectors()``)."""
        return self.replace(vectors=self.view_vectors(), vector_angles=None)

    def circular(self) -> "Geometry":
        """The nominal circular scan (per-view vectors dropped)."""
        return self.replace(vectors=None, vector_angles=None)

    def scaled(self, factor: float) -> "Geometry":
        """All lengths multiplied by ``factor`` (R2-Gaussian's scene rescaling)."""
        f = float(factor)
        vec = None
        if self.per_view:
            vec = np.array(self.vectors)
            vec[:, 3:] *= f
            if self.mode == "cone":
                vec[:, :3] *= f
        return self.replace(
            vectors=vec,
            DSD=self.DSD * f, DSO=self.DSO * f,
            sDetector=tuple(x * f for x in self.sDetector),
            sVoxel=tuple(x * f for x in self.sVoxel),
            offOrigin=tuple(x * f for x in self.offOrigin),
            offDetector=tuple(x * f for x in self.offDetector))

    @property
    def scene_scale(self) -> float:
        """R2-Gaussian's factor 2 / max(sVoxel) that maps the volume into [-1, 1]^3."""
        return 2.0 / max(self.sVoxel)

    def bbox(self) -> np.ndarray:
        """Volume bounding box [[xmin, ymin, zmin], [xmax, ymax, zmax]]."""
        half = np.asarray(self.sVoxel) / 2
        c = np.asarray(self.offOrigin)
        return np.stack([c - half, c + half])

    def voxel_axes(self) -> tuple:
        """Voxel centre coordinates along x, y and z (three 1-D float64 arrays)."""
        return tuple(-s / 2 + (np.arange(n) + 0.5) * (s / n) + o
                     for n, s, o in zip(self.nVoxel, self.sVoxel, self.offOrigin))

    # ---------------------------------------------------------------- dictionaries
    def to_scanner_dict(self) -> dict:
        """The R2-Gaussian / TIGRE ``scanner`` block (angles are not part of it)."""
        return {
            "mode": self.mode, "DSD": self.DSD, "DSO": self.DSO,
            "nDetector": list(self.nDetector), "sDetector": list(self.sDetector),
            "dDetector": list(self.dDetector),
            "nVoxel": list(self.nVoxel), "sVoxel": list(self.sVoxel), "dVoxel": list(self.dVoxel),
            "offOrigin": list(self.offOrigin), "offDetector": list(self.offDetector),
        }

    @classmethod
    def from_scanner_dict(cls, d: dict, angles) -> "Geometry":
        """From an R2-Gaussian / TIGRE scanner block. Extra TIGRE keys (accuracy, filter,
        totalAngle, startAngle, noise settings, dDetector/dVoxel) are accepted; dDetector
        and dVoxel must agree with the sizes when present."""
        required = ("mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel")
        missing = [k for k in required if k not in d]
        if missing:
            raise GeometryError(f"scanner block lacks field(s) {missing}")
        geo = cls(mode=d["mode"], DSD=d["DSD"], DSO=d["DSO"], nDetector=d["nDetector"],
                  sDetector=d["sDetector"], nVoxel=d["nVoxel"], sVoxel=d["sVoxel"],
                  offOrigin=d.get("offOrigin", (0, 0, 0)),
                  offDetector=d.get("offDetector", (0, 0)), angles=angles)
        for key, derived in (("dDetector", geo.dDetector), ("dVoxel", geo.dVoxel)):
            if key in d and not np.allclose(np.asarray(d[key], float).reshape(-1), derived,
                                            rtol=1e-4):
                raise GeometryError(f"{key}={d[key]} disagrees with the sizes/counts ({derived})")
        return geo

    # ---------------------------------------------------------------- rays
    def detector_frame(self, angles=None) -> dict:
        """Per-view frame as float64 arrays [view, 3]: ``source`` (cone beam; for parallel
        beam the point at distance DSD before the detector centre), ``center`` (detector
        centre, offsets included), ``e_u``, ``e_v`` (unit detector axes) and ``normal``
        (unit, from detector towards source)."""
        vec = self.view_vectors(angles)
        e_u = vec[:, 6:9] / np.linalg.norm(vec[:, 6:9], axis=1, keepdims=True)
        e_v = vec[:, 9:12] / np.linalg.norm(vec[:, 9:12], axis=1, keepdims=True)
        normal = np.cross(e_v, e_u)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        center = vec[:, 3:6]
        if self.mode == "cone":
            source = vec[:, 0:3]
        else:
            ray = vec[:, 0:3] / np.linalg.norm(vec[:, 0:3], axis=1, keepdims=True)
            source = center - self.DSD * ray
        normal *= np.sign(np.sum((source - center) * normal, 1))[:, None]
        return {"source": source, "center": center, "e_u": e_u, "e_v": e_v, "normal": normal}

    def rays(self, cos_a, sin_a, v, u):
        """Rays of the circular scan through detector positions (``view_vectors.rays`` of
        the circular views: the one ray formula).

        Works on NumPy arrays (float64 references) and on Dr.Jit arrays (kernels) alike.

        Args:
            cos_a, sin_a: cosine and sine of each ray's view angle.
            v, u: continuous detector coordinates in pixels; pixel (i, j) has its centre
                at (v, u) = (i + 0.5, j + 0.5).
        Returns:
            (origin, direction, length): origin and unit direction as (x, y, z) component
            tuples; ``length`` is the distance from origin to the detector pixel. The origin
            is the source (cone) or the point at distance DSD before the detector (parallel).
        """
        vec = vv.circular_vectors(cos_a, sin_a, self.DSD, self.DSO, self.dDetector,
                                  self.offDetector, self.mode)
        return self.vector_rays(vec, v, u)

    def vector_rays(self, vec, v, u):
        """``view_vectors.rays`` of this scan's detector for the 12 components ``vec``
        (scalars or per-ray arrays, NumPy or Dr.Jit); returns (origin, direction, length)."""
        return vv.rays(vec, v, u, self.nDetector, self.mode, self.DSD)

    def view_tables(self, angles=None):
        """The views' 12 components as float32 Dr.Jit arrays [view] (kernels gather them
        per ray, ``rays_of_views``)."""
        import mitsuba as mi
        vec = self.view_vectors(angles).astype(np.float32)
        return tuple(mi.Float(np.ascontiguousarray(vec[:, k])) for k in range(12))

    def rays_of_views(self, tables, view, v, u, active=True):
        """Dr.Jit rays of detector positions (v, u) of views ``view`` (UInt32 per ray) from
        ``view_tables``; returns (origin, direction, length)."""
        import drjit as dr
        import mitsuba as mi
        vec = [dr.gather(mi.Float, t, view, active) for t in tables]
        return self.vector_rays(vec, v, u)

    def pixel_rays_numpy(self, angles=None):
        """Float64 rays of every pixel centre: origins and unit directions [view, v, u, 3]."""
        vec = self.view_vectors(angles)
        nv, nu = self.nDetector
        V, U = np.meshgrid(np.arange(nv) + 0.5, np.arange(nu) + 0.5, indexing="ij")
        comps = [vec[:, k, None, None] for k in range(12)]
        o, d, _ = self.vector_rays(comps, V[None], U[None])
        shape = (vec.shape[0], nv, nu)
        return (np.stack([np.broadcast_to(x, shape) for x in o], -1),
                np.stack([np.broadcast_to(x, shape) for x in d], -1))


def circular_angles(n_views: int, total_angle: float = 2 * np.pi, start_angle: float = 0.0):
    """``n_views`` equally spaced angles (radians) over ``total_angle``, endpoint excluded."""
    if int(n_views) < 1:
        raise GeometryError(f"n_views must be >= 1, got {n_views}")
    return start_angle + np.arange(int(n_views)) * (total_angle / int(n_views))
