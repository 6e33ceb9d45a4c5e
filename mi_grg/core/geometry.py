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
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

MODES = ("cone", "parallel")


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
        angles:      projection angles [view], radians.
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
        return self.replace(angles=angles)

    def scaled(self, factor: float) -> "Geometry":
        """All lengths multiplied by ``factor`` (R2-Gaussian's scene rescaling)."""
        f = float(factor)
        return self.replace(
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
        beam the point at distance DSO before the origin), ``center`` (detector centre,
        offsets included), ``e_u``, ``e_v`` (unit detector axes) and ``normal`` (unit,
        from detector towards source)."""
        a = self.angles if angles is None else np.asarray(angles, np.float64).reshape(-1)
        c, s, z = np.cos(a), np.sin(a), np.zeros_like(a)
        normal = np.stack([c, s, z], -1)
        e_u = np.stack([-s, c, z], -1)
        e_v = np.stack([z, z, -np.ones_like(a)], -1)
        center = (-(self.DSD - self.DSO) * normal + self.offDetector[0] * e_v
                  + self.offDetector[1] * e_u)
        return {"source": self.DSO * normal, "center": center, "e_u": e_u, "e_v": e_v,
                "normal": normal}

    def rays(self, cos_a, sin_a, v, u):
        """Rays through detector positions; the single place of the ray formula.

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
        dv, du = self.dDetector
        nv, nu = self.nDetector
        su = (u - 0.5 * nu) * du + self.offDetector[1]   # along e_u = (-sin, cos, 0)
        sv = (v - 0.5 * nv) * dv + self.offDetector[0]   # along e_v = (0, 0, -1)
        back = self.DSD - self.DSO
        px = -back * cos_a - su * sin_a
        py = -back * sin_a + su * cos_a
        pz = -sv
        if self.mode == "cone":
            ox, oy, oz = self.DSO * cos_a, self.DSO * sin_a, 0.0 * cos_a
            dx, dy, dz = px - ox, py - oy, pz - oz
            length = _sqrt(dx * dx + dy * dy + dz * dz)
            inv = 1.0 / length
            return (ox, oy, oz), (dx * inv, dy * inv, dz * inv), length
        ox, oy, oz = px + self.DSD * cos_a, py + self.DSD * sin_a, pz
        return (ox, oy, oz), (-cos_a, -sin_a, 0.0 * cos_a), self.DSD + 0.0 * cos_a

    def pixel_rays_numpy(self, angles=None):
        """Float64 rays of every pixel centre: origins and unit directions [view, v, u, 3]."""
        a = self.angles if angles is None else np.asarray(angles, np.float64).reshape(-1)
        nv, nu = self.nDetector
        A, V, U = np.meshgrid(a, np.arange(nv) + 0.5, np.arange(nu) + 0.5, indexing="ij")
        o, d, _ = self.rays(np.cos(A), np.sin(A), V, U)
        return (np.stack(np.broadcast_arrays(*o), -1), np.stack(np.broadcast_arrays(*d), -1))


def _sqrt(x):
    if isinstance(x, np.ndarray) or np.isscalar(x):
        return np.sqrt(x)
    import drjit as dr
    return dr.sqrt(x)


def circular_angles(n_views: int, total_angle: float = 2 * np.pi, start_angle: float = 0.0):
    """``n_views`` equally spaced angles (radians) over ``total_angle``, endpoint excluded."""
    if int(n_views) < 1:
        raise GeometryError(f"n_views must be >= 1, got {n_views}")
    return start_angle + np.arange(int(n_views)) * (total_angle / int(n_views))
