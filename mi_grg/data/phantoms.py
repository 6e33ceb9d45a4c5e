"""Analytic ellipsoid phantoms with closed-form line integrals (the float64 reference).

A phantom is a sum of K ellipsoids, each of constant (additive, possibly negative) density,
like the Shepp-Logan head: the density at a point is the sum of the densities of all
ellipsoids containing it. The line integral of a ray is then
``sum_k density_k * chord_k`` where ``chord_k`` is the length of the ray inside ellipsoid k,
found in closed form from the ray-ellipsoid quadratic.

Coordinates. Ellipsoids are defined in *normalised* coordinates: the phantom lives in
``[-1, 1]^3`` (checked on creation). Evaluated for a ``Geometry`` it is mapped onto the
volume box by ``world = offOrigin + scale * normalised`` with the uniform scale
``scale = min(sVoxel) / 2``, so it fits the box also when the box is not a cube. Densities
are not scaled (units: 1 / length); line integrals are in world units (density x world length).

Range. The built-in phantoms' densities lie in [0, 1] (Shepp-Logan's skull and the outer
shell are 1; the needles and the blobs' densest overlaps stay below 1, by how much depends
on the seed), so their ground-truth voxel averages lie in [0, 1]. They are not stretched to
reach 1 on every grid: a structure thinner than a voxel averages below its density (needles:
max 0.965 at 64^3, 0.860 at 32^3; Shepp-Logan: 1.0 at 64^3, 0.972 at 32^3). Stretching would
make the phantom depend on the grid and break the match between a data set and the
``ct_phantom`` medium of its scene file; PSNR with data range 1 stays comparable across
grids.

Axis orders: points ``[..., 3]`` are (x, y, z); volumes ``[x, y, z]``; projections
``[view, v, u]``. All computations are float64 NumPy, vectorised over rays / voxels and
looping only over ellipsoids.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mi_grg.core.geometry import Geometry

PHANTOMS = ("shepp", "needles", "shells", "blobs")

_RAY_CHUNK = 1 << 16        # rays per vectorised batch (keeps temporaries ~ tens of MB)
_VOXEL_CHUNK = 1 << 20      # voxel centres per classification batch
_POINT_CHUNK = 1 << 20      # sub-voxel points per supersampling batch
_BAND_EPS = 1e-9            # slack on the inside/outside classification of whole voxels
_SNAP = 1e-9                # |sum| below this is round-off of cancelling densities -> 0


def _as_array(name, value, shape_tail, k=None):
    want = f"[{'K' if k is None else k}, {', '.join(map(str, shape_tail))}]"
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers of shape {want}, got {value!r}") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail or (
            k is not None and arr.shape[0] != k):
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


@dataclass(frozen=True, eq=False)   # arrays: compare fields explicitly
class EllipsoidPhantom:
    """K ellipsoids of additive constant density, in normalised coordinates ``[-1, 1]^3``.

    Attributes (float64, read-only):
        centres:   [K, 3] ellipsoid centres (x, y, z), normalised units.
        semi_axes: [K, 3] semi-axis lengths (> 0), normalised units, along the ellipsoid's
                   local axes.
        rotations: [K, 3, 3] rotation matrices; column j is the direction of local axis j in
                   the phantom frame, i.e. local coordinates are ``R^T (x - centre)``.
                   Must be proper rotations (orthonormal, det +1).
        densities: [K] additive density of each ellipsoid (1 / length; may be negative).
        name:      label recorded in simulated cases.

    Every ellipsoid's axis-aligned bounding box must lie within ``[-1, 1]^3``.
    """

    centres: np.ndarray
    semi_axes: np.ndarray
    rotations: np.ndarray
    densities: np.ndarray
    name: str = "custom"

    def __post_init__(self):
        c = _as_array("centres", self.centres, (3,))
        k = c.shape[0]
        if k == 0:
            raise ValueError("a phantom needs at least one ellipsoid")
        a = _as_array("semi_axes", self.semi_axes, (3,), k)
        if np.any(a <= 0):
            raise ValueError("semi_axes must be > 0")
        r = _as_array("rotations", self.rotations, (3, 3), k)
        err = np.abs(np.einsum("kji,kjl->kil", r, r) - np.eye(3)).max()
        if err > 1e-9:
            raise ValueError(f"rotations must be orthonormal [K, 3, 3] (max |R^T R - I| = {err:.3g})")
        if np.any(np.linalg.det(r) <= 0):
            raise ValueError("rotations must have determinant +1 (proper rotations)")
        try:
            rho = np.array(self.densities, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"densities must be [K] numbers, got {self.densities!r}") from None
        if rho.shape != (k,) or not np.all(np.isfinite(rho)):
            raise ValueError(f"densities must be [K={k}] finite numbers, got shape {rho.shape}")
        half = _aabb_half_extents(a, r)
        lo, hi = c - half, c + half
        bad = np.nonzero(np.any(lo < -1 - 1e-12, 1) | np.any(hi > 1 + 1e-12, 1))[0]
        if bad.size:
            raise ValueError(f"ellipsoid(s) {bad.tolist()} leave the normalised box [-1, 1]^3")
        for name, arr in (("centres", c), ("semi_axes", a), ("rotations", r), ("densities", rho)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "name", str(self.name))

    def __len__(self):
        return int(self.densities.size)

    # ------------------------------------------------------------------ mapping
    @staticmethod
    def world_transform(geometry: Geometry):
        """(origin [3], scale) with ``world = origin + scale * normalised``: the box centre
        ``offOrigin`` and ``min(sVoxel) / 2``."""
        return np.asarray(geometry.offOrigin, np.float64), min(geometry.sVoxel) / 2.0

    def frames(self) -> np.ndarray:
        """[K, 3, 3] per ellipsoid the matrix B = R diag(1/a): ``(x - c) @ B`` maps a
        normalised point x (row vector) to the ellipsoid's unit-sphere frame, so x is inside
        ellipsoid k iff ``|(x - c_k) @ B_k|^2 <= 1``."""
        return self.rotations / self.semi_axes[:, None, :]

    # ------------------------------------------------------------------ density
    def density(self, points, geometry: Geometry) -> np.ndarray:
        """Density at world points ``[..., 3]`` (x, y, z), float64 ``[...]``.

        Points on an ellipsoid's surface count as inside it. Sums within 1e-9 of 0 are set
        to 0 (round-off of cancelling densities)."""
        pts = np.asarray(points, np.float64)
        if pts.shape[-1:] != (3,):
            raise ValueError(f"points must have shape [..., 3], got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("points must be finite (world coordinates)")
        o, s = self.world_transform(geometry)
        flat = ((pts.reshape(-1, 3) - o) / s)
        out = np.zeros(flat.shape[0])
        for i in range(0, flat.shape[0], _POINT_CHUNK):
            out[i:i + _POINT_CHUNK] = self._density_normalised(flat[i:i + _POINT_CHUNK])
        return _snap_zero(out).reshape(pts.shape[:-1])

    def _density_normalised(self, p):
        out = np.zeros(p.shape[0])
        for c, b, rho in zip(self.centres, self.frames(), self.densities):
            q = (p - c) @ b
            out += np.where(np.einsum("ij,ij->i", q, q) <= 1.0, rho, 0.0)
        return out

    # ------------------------------------------------------------------ rays
    def ray_integrals(self, origins, directions, geometry: Geometry, lengths=None) -> np.ndarray:
        """Closed-form integrals of the density along ray segments, float64 ``[...]``.

        Args:
            origins:    [..., 3] world start points.
            directions: [..., 3] world directions (normalised here; must be non-zero).
            geometry:   places the phantom (see module docstring).
            lengths:    [...] world segment lengths (>= 0), or None for half-lines.
        Returns:
            sum over ellipsoids of density x (length of the segment inside it); segments
            that start or end inside an ellipsoid are clipped, grazing and missing rays
            give exactly 0.
        """
        o = np.asarray(origins, np.float64)
        d = np.asarray(directions, np.float64)
        if o.shape[-1:] != (3,) or d.shape != o.shape:
            raise ValueError(f"origins and directions must both be [..., 3], got {o.shape} "
                             f"and {d.shape}")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
            raise ValueError("origins and directions must be finite (world coordinates)")
        norm = np.linalg.norm(d, axis=-1, keepdims=True)
        if np.any(norm <= 0):
            raise ValueError("directions must be non-zero")
        d = d / norm
        if lengths is None:
            ln = np.full(o.shape[:-1], np.inf)
        else:
            ln = np.broadcast_to(np.asarray(lengths, np.float64), o.shape[:-1])
            if np.any(np.isnan(ln)) or np.any(ln < 0):
                raise ValueError("lengths must be >= 0 (world units) and not NaN")
        shape = o.shape[:-1]
        origin, scale = self.world_transform(geometry)
        o = (o.reshape(-1, 3) - origin) / scale    # normalised start points
        d = d.reshape(-1, 3) / scale               # normalised step per world unit of length
        ln = ln.reshape(-1)
        out = np.zeros(o.shape[0])
        for i in range(0, o.shape[0], _RAY_CHUNK):
            sl = slice(i, i + _RAY_CHUNK)
            out[sl] = self._chords(o[sl], d[sl], ln[sl])
        return out.reshape(shape)

    def _chords(self, o, d, ln):
        out = np.zeros(o.shape[0])
        for c, b, rho in zip(self.centres, self.frames(), self.densities):
            p = (o - c) @ b      # start point in the unit-sphere frame
            w = d @ b            # direction there (not unit); t stays the world length
            ww = np.einsum("ij,ij->i", w, w)
            cr = np.cross(p, w)
            # |p + t w|^2 = 1 has roots mid -/+ half with half = sqrt(ww - |p x w|^2) / ww;
            # the cross-product form avoids the cancellation of (p.w)^2 - ww (p.p - 1).
            disc = ww - np.einsum("ij,ij->i", cr, cr)
            half = np.sqrt(np.maximum(disc, 0.0)) / ww   # disc < 0: the line misses -> 0
            mid = -np.einsum("ij,ij->i", p, w) / ww
            cut_lo = np.maximum(half - mid, 0.0)           # part before the segment start
            cut_hi = np.maximum(mid + half - ln, 0.0)      # part after the segment end
            out += rho * np.maximum(2.0 * half - cut_lo - cut_hi, 0.0)
        return out

    def line_integrals(self, geometry: Geometry, angles=None) -> np.ndarray:
        """Exact projections ``[view, v, u]`` (float64, density x world length) of every
        pixel centre, source (or parallel-beam start point) to detector pixel, through
        the ray formula (``Geometry.vector_rays``; per-view scans included). ``angles`` (radians) default to ``geometry.angles``."""
        a = geometry.angles if angles is None else np.asarray(angles, np.float64).reshape(-1)
        if a.size == 0 or not np.all(np.isfinite(a)):
            raise ValueError("angles must be a non-empty array of finite radians")
        nv, nu = geometry.nDetector
        out = np.empty((a.size, nv, nu))
        vv, uu = np.meshgrid(np.arange(nv) + 0.5, np.arange(nu) + 0.5, indexing="ij")
        vec = geometry.view_vectors(a)
        for i in range(a.size):
            o, d, length = geometry.vector_rays(list(vec[i]), vv, uu)
            o = np.stack(np.broadcast_arrays(*o), -1)
            d = np.stack(np.broadcast_arrays(*d), -1)
            out[i] = self.ray_integrals(o, d, geometry, np.broadcast_to(length, vv.shape))
        return out

    # ------------------------------------------------------------------ voxels
    def voxelize(self, geometry: Geometry, supersample: int = 4) -> np.ndarray:
        """Ground-truth volume ``[x, y, z]`` float32 on ``geometry``'s voxel grid.

        Each voxel holds the mean density over ``supersample^3`` sub-voxel points (centres
        of a regular ``supersample^3`` subdivision of the voxel). Voxels that lie wholly
        inside or outside an ellipsoid (decided with a Lipschitz bound on the ellipsoid's
        quadratic form plus a tiny slack) take 1 or 0 for it without sampling; only voxels
        crossing a surface are supersampled, which gives the same means as sampling all.
        Values within 1e-9 of 0 are set to 0 (round-off of cancelling densities); nothing
        else is clipped.
        """
        s_int = int(supersample)
        if s_int != supersample or s_int < 1:
            raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
        origin, scale = self.world_transform(geometry)
        axes = [(ax - o) / scale for ax, o in zip(geometry.voxel_axes(), origin)]
        dv = np.asarray(geometry.dVoxel) / scale
        frac = (np.arange(s_int) + 0.5) / s_int - 0.5
        sub = np.stack(np.meshgrid(frac * dv[0], frac * dv[1], frac * dv[2], indexing="ij"),
                       -1).reshape(-1, 3)                       # [S^3, 3] offsets
        reach = float(np.linalg.norm(sub, axis=1).max())        # farthest sub-point
        vol = np.zeros(geometry.nVoxel)
        half_ext = _aabb_half_extents(self.semi_axes, self.rotations)
        for c, b, a, he, rho in zip(self.centres, self.frames(), self.semi_axes, half_ext,
                                    self.densities):
            lip = 1.0 / a.min()     # |grad sqrt(q)| <= 1 / min semi-axis
            rng = [np.nonzero((ax + dv[j] / 2 >= c[j] - he[j]) & (ax - dv[j] / 2 <= c[j] + he[j]))[0]
                   for j, ax in enumerate(axes)]
            if any(r.size == 0 for r in rng):
                continue
            (x0, x1), (y0, y1), (z0, z1) = [(int(r[0]), int(r[-1]) + 1) for r in rng]
            per_x = max(1, _VOXEL_CHUNK // ((y1 - y0) * (z1 - z0)))
            for xs in range(x0, x1, per_x):
                xe = min(xs + per_x, x1)
                dx = axes[0][xs:xe, None, None] - c[0]
                dy = axes[1][None, y0:y1, None] - c[1]
                dz = axes[2][None, None, z0:z1] - c[2]
                q = sum((dx * b[0, j] + dy * b[1, j] + dz * b[2, j]) ** 2 for j in range(3))
                r = np.sqrt(q)
                inside = r + reach * lip < 1.0 - _BAND_EPS
                band = ~inside & (r - reach * lip <= 1.0 + _BAND_EPS)
                slab = vol[xs:xe, y0:y1, z0:z1]
                slab[inside] += rho
                bi = np.nonzero(band)
                if bi[0].size == 0:
                    continue
                centres = np.stack([axes[0][xs + bi[0]], axes[1][y0 + bi[1]], axes[2][z0 + bi[2]]], -1)
                fill = np.empty(centres.shape[0])
                per = max(1, _POINT_CHUNK // sub.shape[0])
                for i in range(0, centres.shape[0], per):
                    pts = centres[i:i + per, None, :] + sub[None] - c     # [n, S^3, 3]
                    qq = pts @ b
                    fill[i:i + per] = (np.einsum("nsj,nsj->ns", qq, qq) <= 1.0).mean(1)
                slab[bi] += rho * fill
        return _snap_zero(vol).astype(np.float32)

    def bounds(self) -> tuple:
        """(lo, hi): the normalised axis-aligned bounding box of the whole phantom."""
        half = _aabb_half_extents(self.semi_axes, self.rotations)
        return (self.centres - half).min(0), (self.centres + half).max(0)


def _snap_zero(x):
    """Set round-off residues of cancelling densities (1 - 0.8 - 0.2 = -5.6e-17 in float64)
    to exactly 0; only |x| < 1e-9, so real excursions below 0 stay visible."""
    x[np.abs(x) < _SNAP] = 0.0
    return x


def _aabb_half_extents(semi_axes, rotations):
    """Half-extents [K, 3] of each ellipsoid's axis-aligned bounding box."""
    return np.sqrt(np.einsum("kij,kj->ki", rotations ** 2, semi_axes ** 2))


# ====================================================================== families
def _rot_z(deg):
    t = math.radians(deg)
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(deg):
    t = math.radians(deg)
    c, s = math.cos(t), math.sin(t)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _frame_from_axis(u):
    """A proper rotation whose third column is the unit vector ``u``."""
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2, u], 1)


def _random_rotation(rng):
    """Uniformly distributed rotation (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# 3D modified Shepp-Logan head: Toft's modified intensities with the 3D semi-axes/centres of
# Schabel's phantom3d (TIGRE sl3d "toft-schabel", ODL's 3D modified phantom). Each ellipsoid
# is rotated about z around its own centre by phi (local axis a along (cos phi, sin phi, 0)),
# as ODL does; Schabel's MATLAB code also tilts the ventricles by psi = 10 deg and rotates
# their centres, which we do not. Region values: skull 1.0, brain 0.2, ventricles 0.0,
# small features 0.3 (or 0.4 where two overlap) -- all within [0, 1].
_SHEPP = (
    #  A      a       b      c      x0     y0       z0     phi(deg)
    (1.0,  0.6900, 0.920, 0.810,  0.00,  0.0000,  0.00,   0.0),
    (-0.8, 0.6624, 0.874, 0.780,  0.00, -0.0184,  0.00,   0.0),
    (-0.2, 0.1100, 0.310, 0.220,  0.22,  0.0000,  0.00, -18.0),
    (-0.2, 0.1600, 0.410, 0.280, -0.22,  0.0000,  0.00,  18.0),
    (0.1,  0.2100, 0.250, 0.410,  0.00,  0.3500, -0.15,   0.0),
    (0.1,  0.0460, 0.046, 0.050,  0.00,  0.1000,  0.25,   0.0),
    (0.1,  0.0460, 0.046, 0.050,  0.00, -0.1000,  0.25,   0.0),
    (0.1,  0.0460, 0.023, 0.050, -0.08, -0.6050,  0.00,   0.0),
    (0.1,  0.0230, 0.023, 0.020,  0.00, -0.6060,  0.00,   0.0),
    (0.1,  0.0230, 0.046, 0.020,  0.06, -0.6050,  0.00,   0.0),
)


def _shepp():
    t = np.array(_SHEPP)
    return EllipsoidPhantom(centres=t[:, 4:7], semi_axes=t[:, 1:4],
                            rotations=np.stack([_rot_z(p) for p in t[:, 7]]),
                            densities=t[:, 0], name="shepp")


def _ball_side(p, r, c, b, a_min):
    """+1 if the ball (p, r) is surely inside the ellipsoid (c, B), -1 if surely outside,
    0 if it may cross the surface (Lipschitz bound of sqrt(q), constant 1 / a_min)."""
    g = (p - c) @ b
    rq = math.sqrt(float(g @ g))
    if rq + r / a_min < 1.0 - 1e-6:
        return 1
    if rq - r / a_min > 1.0 + 1e-6:
        return -1
    return 0


def _segment_distance(p0, p1, q0, q1, n=64):
    """Lower bound on the distance between segments [p0, p1] and [q0, q1] (dense sampling
    minus the sampling gap)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    a = p0 + t * (p1 - p0)
    b = q0 + t * (q1 - q0)
    dmin = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min()
    gap = 0.5 * (np.linalg.norm(p1 - p0) + np.linalg.norm(q1 - q0)) / (n - 1)
    return dmin - gap


def _needles(seed):
    """A faint body (0.1) holding 10 non-touching needles (0.5-0.9) of radius 0.02-0.04
    (1-2 % of the volume's edge of 2) and half-length 0.2-0.45, randomly oriented.
    Needles are kept apart and inside the body, so densities stay within [0, 1]."""
    rng = np.random.default_rng(seed)
    body_axes = np.array([0.85, 0.80, 0.75])
    body_b = np.eye(3) / body_axes
    cen, axes, rots, rho = [np.zeros(3)], [body_axes], [np.eye(3)], [0.1]
    caps = []   # (end0, end1, radius) of the capsules enclosing placed needles
    tries = 0
    while len(caps) < 10:
        tries += 1
        if tries > 20000:
            raise RuntimeError("could not place the needles; this is a bug")
        r = rng.uniform(0.02, 0.04)
        half = rng.uniform(0.2, 0.45)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        p = rng.uniform(-1, 1, 3) * body_axes
        e0, e1 = p - half * u, p + half * u
        # The needle lies in the capsule around its axis; the set of ball centres inside the
        # (convex) body is convex, so checking both end balls keeps the whole capsule inside.
        if any(_ball_side(e, r + 0.02, np.zeros(3), body_b, body_axes.min()) != 1
               for e in (e0, e1)):
            continue
        if any(_segment_distance(e0, e1, f0, f1) <= r + rr + 0.02 for f0, f1, rr in caps):
            continue
        caps.append((e0, e1, r))
        cen.append(p)
        axes.append(np.array([r, r, half]))
        rots.append(_frame_from_axis(u))
        rho.append(rng.uniform(0.5, 0.9))
    return EllipsoidPhantom(centres=np.array(cen), semi_axes=np.array(axes),
                            rotations=np.array(rots), densities=np.array(rho), name="needles")


# Nested shells: (centre, outer semi-axes, thickness, rotation, density). Containment is by
# construction: the inner ellipsoid has the same centre and rotation and smaller semi-axes,
# and each shell's outer bounding sphere (max semi-axis + centre offset) lies inside the
# inscribed sphere (min semi-axis) of the next outer shell's inner ellipsoid.
_SHELLS = (
    ((0.00, 0.00, 0.00), (0.88, 0.80, 0.72), 0.06, _rot_z(15.0), 0.5),
    ((0.05, -0.03, 0.02), (0.55, 0.48, 0.58), 0.07, _rot_z(20.0) @ _rot_x(30.0), 0.8),
    ((-0.08, 0.05, 0.00), (0.26, 0.20, 0.30), 0.06, _rot_x(-25.0), 1.0),
)


def _shells(seed):
    """Three nested ellipsoidal shells (0.5, 0.8, 1.0; empty gaps between them) plus 8
    small high-contrast inclusions (0.6-1.0, radius 0.03-0.07) placed by ``seed`` in the
    empty gaps, apart from each other and from the shell walls."""
    rng = np.random.default_rng(seed)
    cen, axes, rots, rho = [], [], [], []
    for c, a, th, rot, dens in _SHELLS:
        a = np.array(a)
        for aa, sign in ((a, 1.0), (a - th, -1.0)):
            cen.append(np.array(c))
            axes.append(aa)
            rots.append(rot)
            rho.append(sign * dens)
    walls = [(c, r / a[None, :], a.min(), d) for c, a, r, d in zip(cen, axes, rots, rho)]
    placed = []
    tries = 0
    while len(placed) < 8:
        tries += 1
        if tries > 50000:
            raise RuntimeError("could not place the inclusions; this is a bug")
        r = rng.uniform(0.03, 0.07)
        p = rng.uniform(-0.9, 0.9, 3)
        sides = [_ball_side(p, r + 0.01, c, b, am) for c, b, am, _ in walls]
        if 0 in sides or sides[0] != 1:
            continue
        if abs(sum(d for (_, _, _, d), s in zip(walls, sides) if s == 1)) > 1e-12:
            continue    # not in an empty gap
        if any(np.linalg.norm(p - q) <= r + rq + 0.02 for q, rq in placed):
            continue
        placed.append((p, r))
        cen.append(p)
        axes.append(r * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0)]))
        rots.append(_random_rotation(rng))
        rho.append(rng.uniform(0.6, 1.0))
    return EllipsoidPhantom(centres=np.array(cen), semi_axes=np.array(axes),
                            rotations=np.array(rots), densities=np.array(rho), name="shells")


def _blobs(seed):
    """A faint body (0.1) holding 14 overlapping blobs (ellipsoids of density 0.1-0.3,
    semi-axes 0.08-0.3) at random places and orientations inside it. A blob may overlap at
    most two earlier ones (by bounding spheres), so no point lies in more than three blobs
    (a fourth would be the later neighbour of three) and densities stay within [0, 1]."""
    rng = np.random.default_rng(seed)
    body_axes = np.array([0.85, 0.80, 0.75])
    body_b = np.eye(3) / body_axes
    cen, axes, rots, rho = [np.zeros(3)], [body_axes], [np.eye(3)], [0.1]
    spheres = []   # (centre, bounding radius) of placed blobs
    tries = 0
    while len(spheres) < 14:
        tries += 1
        if tries > 20000:
            raise RuntimeError("could not place the blobs; this is a bug")
        a = rng.uniform(0.08, 0.3, 3)
        p = rng.uniform(-1, 1, 3) * body_axes
        if _ball_side(p, a.max() + 0.02, np.zeros(3), body_b, body_axes.min()) != 1:
            continue
        if sum(np.linalg.norm(p - q) < a.max() + r for q, r in spheres) > 2:
            continue
        spheres.append((p, a.max()))
        cen.append(p)
        axes.append(a)
        rots.append(_random_rotation(rng))
        rho.append(rng.uniform(0.1, 0.3))
    return EllipsoidPhantom(centres=np.array(cen), semi_axes=np.array(axes),
                            rotations=np.array(rots), densities=np.array(rho), name="blobs")


def make_phantom(name: str, seed: int = 0) -> EllipsoidPhantom:
    """One of ``PHANTOMS``: ``"shepp"`` (3D modified Shepp-Logan; ``seed`` unused),
    ``"needles"`` (random needles on a faint body), ``"shells"`` (nested shells with
    random small inclusions) or ``"blobs"`` (overlapping ellipsoids on a faint body).
    Densities of every family lie in [0, 1]."""
    if name == "shepp":
        return _shepp()
    if name == "needles":
        return _needles(seed)
    if name == "shells":
        return _shells(seed)
    if name == "blobs":
        return _blobs(seed)
    raise ValueError(f"unknown phantom {name!r}; valid names: {', '.join(PHANTOMS)}")
