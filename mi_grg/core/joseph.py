"""Ray-driven voxel forward projector (Joseph's method) and its exact adjoint, in Dr.Jit.

Method (Joseph 1982): every detector pixel casts the ray of ``Geometry.rays`` (the one
ray formula; pixel centres at index + 0.5). In continuous voxel-index space
``q = (p - lo) / dVoxel - 1/2`` (voxel centres at integer q) the ray's *dominant axis* k
(largest |dq_k/dt|) is stepped one voxel-centre plane at a time; on each plane the volume
is interpolated bilinearly in the two other axes (zero outside the volume) and weighted
by the ray length between planes, ``dVoxel_k / |d_k|``. So the step is one voxel along the
dominant axis (not a fixed length), and a sample costs four gathers. The ray is first
clipped to the volume box ``q in [-1/2, n - 1/2]^3`` (slab method) so that only planes
it crosses inside the box are visited.

The back projector is the *transposed scatter* of exactly the same weights (each gather
becomes a ``scatter_add``): it is the exact adjoint A^T of the forward operator A (up to
float32 rounding), which SART/ASD-POCS need. Reverse-mode AD of the forward would give the
same operator, but Dr.Jit cannot differentiate symbolic loops in reverse without storing
every iteration, so the explicit scatter is both simpler and faster.

Units: volumes are densities [x, y, z] (1/length); projections are line integrals
[view, v, u] (density x length), in the geometry's length unit.

Memory: one kernel per chunk of at most ``MAX_RAYS`` rays (whole views), so memory is the
volume, its back-projection accumulator and one chunk of projections.
"""
from __future__ import annotations

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core.geometry import Geometry

#: Rays per kernel launch (whole views per chunk); bounds temporary memory.
MAX_RAYS = 1 << 22


# ---------------------------------------------------------------- validation
def check_volume(volume, geometry: Geometry, name: str = "volume") -> np.ndarray:
    """``volume`` as a C-contiguous float32 array [x, y, z] = nVoxel; NaN/Inf rejected."""
    if isinstance(volume, mi.TensorXf):
        volume = volume.numpy()
    arr = np.asarray(volume)
    expected = tuple(geometry.nVoxel)
    if arr.shape != expected:
        raise ValueError(f"{name} must have shape [x, y, z] = nVoxel = {expected}, got "
                         f"{arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or Inf values (expected finite densities)")
    return arr


def check_projections(proj, geometry: Geometry, angles=None, name: str = "proj"):
    """``proj`` as a C-contiguous float32 array [view, v, u] = (len(angles), *nDetector)."""
    if isinstance(proj, mi.TensorXf):
        proj = proj.numpy()
    arr = np.asarray(proj)
    n_views = geometry.n_views if angles is None else len(np.reshape(angles, -1))
    expected = (n_views, *geometry.nDetector)
    if arr.shape != expected:
        raise ValueError(f"{name} must have shape [view, v, u] = (len(angles), *nDetector) = "
                         f"{expected}, got {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} holds no views (need at least one projection)")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or Inf values (expected finite line integrals)")
    return arr


def check_angles(angles, geometry: Geometry) -> np.ndarray:
    """Angles (radians) as float64 [view]; the geometry's own when ``angles`` is None."""
    if angles is None:
        return np.asarray(geometry.angles, np.float64)
    a = np.asarray(angles, np.float64).reshape(-1)
    if a.size == 0:
        raise ValueError("angles holds no views (need at least one angle, radians)")
    if not np.all(np.isfinite(a)):
        raise ValueError("angles must be finite (radians)")
    return a


# ---------------------------------------------------------------- operator
class JosephProjector:
    """Joseph forward projector A and its exact adjoint A^T for one geometry.

    Works on flat Dr.Jit arrays: volumes ``mi.Float`` of size prod(nVoxel) in [x, y, z]
    C order, projections ``mi.Float`` of size n_views * nv * nu in [view, v, u] C order.
    Angles are passed per call (numpy, radians) so that subsets reuse the compiled kernels.
    """

    def __init__(self, geometry: Geometry):
        self.geo = geometry
        self.n_vox = int(np.prod(geometry.nVoxel))
        self.n_pix = int(geometry.nDetector[0] * geometry.nDetector[1])

    # -- helpers ---------------------------------------------------------
    def _chunks(self, n_views):
        per = max(1, MAX_RAYS // self.n_pix)
        for start in range(0, n_views, per):
            yield start, min(n_views, start + per)

    def angle_tables(self, angles):
        """The views' 12 vector components (float32 tables, ``Geometry.view_tables``): a
        circular scan and the same scan given as vectors run the same arithmetic."""
        return self.geo.view_tables(np.asarray(angles, np.float64).reshape(-1))

    def _setup(self, tables, n_rays, view0):
        """Per-ray Joseph set-up for rays view0 * n_pix + [0, n_rays).

        Returns a dict: q0 along the dominant axis k and the two others (b, c), the
        index-space direction components, strides and sizes, plane range [i0, i1] and the
        sample weight (ray length per plane)."""
        geo = self.geo
        nv, nu = geo.nDetector
        nx, ny, nz = geo.nVoxel
        dvx, dvy, dvz = geo.dVoxel
        lo = np.asarray(geo.offOrigin) - np.asarray(geo.sVoxel) / 2
        Float, Int, UInt = mi.Float, mi.Int32, mi.UInt32

        r = dr.arange(UInt, n_rays)
        view = r // self.n_pix + dr.opaque(UInt, view0)
        pix = r % self.n_pix
        iv, iu = pix // nu, pix % nu
        (ox, oy, oz), (dx, dy, dz), _ = geo.rays_of_views(tables, view, Float(iv) + 0.5,
                                                          Float(iu) + 0.5)

        # continuous voxel-index space, voxel centres at integers
        q = [(ox - lo[0]) / dvx - 0.5, (oy - lo[1]) / dvy - 0.5, (oz - lo[2]) / dvz - 0.5]
        e = [dx / dvx, dy / dvy, dz / dvz]
        n = (nx, ny, nz)
        # slab clipping against [-1/2, n - 1/2] per axis
        tmin = Float(-dr.inf) if geo.mode == "parallel" else Float(0.0)
        tmax = Float(dr.inf)
        for a in range(3):
            flat = dr.abs(e[a]) < 1e-12
            inside = (q[a] >= -0.5) & (q[a] <= n[a] - 0.5)
            inv = 1.0 / dr.select(flat, 1.0, e[a])
            t1 = (-0.5 - q[a]) * inv
            t2 = (n[a] - 0.5 - q[a]) * inv
            near = dr.select(flat, dr.select(inside, -dr.inf, dr.inf), dr.minimum(t1, t2))
            far = dr.select(flat, dr.select(inside, dr.inf, -dr.inf), dr.maximum(t1, t2))
            tmin = dr.maximum(tmin, near)
            tmax = dr.minimum(tmax, far)
        hit = tmin < tmax

        ax, ay, az = dr.abs(e[0]), dr.abs(e[1]), dr.abs(e[2])
        kx = (ax >= ay) & (ax >= az)
        ky = ~kx & (ay >= az)
        # (k, b, c) = (x, y, z) | (y, x, z) | (z, x, y)
        def pick(vx, vy, vz):
            return dr.select(kx, vx, dr.select(ky, vy, vz))
        sx, sy, sz = ny * nz, nz, 1
        st = {
            "qk": pick(q[0], q[1], q[2]), "ek": pick(e[0], e[1], e[2]),
            "qb": pick(q[1], q[0], q[0]), "eb": pick(e[1], e[0], e[0]),
            "qc": pick(q[2], q[2], q[1]), "ec": pick(e[2], e[2], e[1]),
            "sk": pick(Int(sx), Int(sy), Int(sz)), "sb": pick(Int(sy), Int(sx), Int(sx)),
            "sc": pick(Int(sz), Int(sz), Int(sy)),
            "nb": pick(Int(ny), Int(nx), Int(nx)), "nc": pick(Int(nz), Int(nz), Int(ny)),
        }
        nk = pick(Int(nx), Int(ny), Int(nz))
        ka = st["qk"] + tmin * st["ek"]
        kb = st["qk"] + tmax * st["ek"]
        i0 = dr.maximum(Int(dr.ceil(dr.minimum(ka, kb))), 0)
        i1 = dr.minimum(Int(dr.floor(dr.maximum(ka, kb))), nk - 1)
        st["i0"] = dr.select(hit, i0, 0)
        st["i1"] = dr.select(hit, i1, -1)
        # Ray length between consecutive planes. The dominant component of a unit
        # direction is >= 1/sqrt(3) / dVoxel_k, so no zero guard is needed (and
        # dr.abs(dr.select(dr.abs(x) > 0, x, 1.0)) is miscompiled by Dr.Jit 1.5.0: it
        # returns x, sign included).
        st["w"] = 1.0 / pick(ax, ay, az)
        st["inv_ek"] = 1.0 / st["ek"]
        return st

    @staticmethod
    def _sample(st, i):
        """Bilinear footprint of plane i: four flat indices, weights and validity masks."""
        Int, UInt, Float = mi.Int32, mi.UInt32, mi.Float
        t = (Float(i) - st["qk"]) * st["inv_ek"]
        qb = dr.fma(t, st["eb"], st["qb"])
        qc = dr.fma(t, st["ec"], st["qc"])
        fb, fc = dr.floor(qb), dr.floor(qc)
        ib, ic = Int(fb), Int(fc)
        wb1, wc1 = qb - fb, qc - fc
        wb0, wc0 = 1.0 - wb1, 1.0 - wc1
        mb0 = (ib >= 0) & (ib < st["nb"])
        mb1 = (ib >= -1) & (ib < st["nb"] - 1)
        mc0 = (ic >= 0) & (ic < st["nc"])
        mc1 = (ic >= -1) & (ic < st["nc"] - 1)
        base = i * st["sk"] + ib * st["sb"] + ic * st["sc"]
        idx = (UInt(base), UInt(base + st["sb"]), UInt(base + st["sc"]),
               UInt(base + st["sb"] + st["sc"]))
        w = st["w"]
        wts = (w * wb0 * wc0, w * wb1 * wc0, w * wb0 * wc1, w * wb1 * wc1)
        msk = (mb0 & mc0, mb1 & mc0, mb0 & mc1, mb1 & mc1)
        return idx, wts, msk

    @dr.syntax
    def _forward_chunk(self, vol, tables, n_rays, view0):
        st = self._setup(tables, n_rays, view0)
        i = mi.Int32(st["i0"])
        acc = dr.zeros(mi.Float, n_rays)
        while i <= st["i1"]:
            idx, wts, msk = self._sample(st, i)
            acc += (wts[0] * dr.gather(mi.Float, vol, idx[0], msk[0])
                    + wts[1] * dr.gather(mi.Float, vol, idx[1], msk[1])
                    + wts[2] * dr.gather(mi.Float, vol, idx[2], msk[2])
                    + wts[3] * dr.gather(mi.Float, vol, idx[3], msk[3]))
            i += 1
        return acc

    @dr.syntax
    def _adjoint_chunk(self, out, proj, tables, n_rays, view0, mode):
        st = self._setup(tables, n_rays, view0)
        y = dr.gather(mi.Float, proj, dr.arange(mi.UInt32, n_rays))
        i = mi.Int32(st["i0"])
        live = (y != 0) & (st["i0"] <= st["i1"])
        while live & (i <= st["i1"]):
            idx, wts, msk = self._sample(st, i)
            for j in range(4):
                dr.scatter_add(out, y * wts[j], idx[j], msk[j], mode=mode)
            i += 1

    def _reduce_mode(self):
        # Expand (per-thread copies, no atomics) is much faster on the LLVM backend; it
        # costs thread_count copies of the volume, so only while that stays modest.
        if dr.backend_v(mi.Float) == dr.JitBackend.LLVM and \
                self.n_vox * dr.thread_count() <= (1 << 28):
            return dr.ReduceMode.Expand
        return dr.ReduceMode.Auto

    # -- public operator -------------------------------------------------
    def forward(self, vol, angles) -> "mi.Float":
        """A x: flat volume -> flat projections [view, v, u] for ``angles`` (radians)."""
        angles = np.asarray(angles, np.float64).reshape(-1)
        tables = self.angle_tables(angles)
        n_views = angles.size
        chunks = list(self._chunks(n_views))
        if len(chunks) == 1:
            out = self._forward_chunk(vol, tables, n_views * self.n_pix, 0)
            dr.eval(out)
            return out
        out = dr.zeros(mi.Float, n_views * self.n_pix)
        for a, b in chunks:
            n = (b - a) * self.n_pix
            val = self._forward_chunk(vol, tables, n, a)
            dr.scatter(out, val, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, a * self.n_pix))
            dr.eval(out)
        return out

    def adjoint(self, proj, angles) -> "mi.Float":
        """A^T y: flat projections [view, v, u] for ``angles`` -> flat volume [x, y, z]."""
        angles = np.asarray(angles, np.float64).reshape(-1)
        tables = self.angle_tables(angles)
        out = dr.zeros(mi.Float, self.n_vox)
        mode = self._reduce_mode()
        for a, b in self._chunks(angles.size):
            n = (b - a) * self.n_pix
            part = proj if (a == 0 and b == angles.size) else dr.gather(
                mi.Float, proj, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, a * self.n_pix))
            self._adjoint_chunk(out, part, tables, n, a, mode)
            dr.eval(out)
        return out


# ---------------------------------------------------------------- numpy-facing API
def forward_project_dr(volume, geometry: Geometry, angles=None) -> "mi.TensorXf":
    """Joseph forward projection as ``mi.TensorXf`` [view, v, u] (line integrals).

    Args:
        volume: densities [x, y, z] = geometry.nVoxel (numpy or mi.TensorXf), 1/length.
        geometry: the scan; ``angles`` (radians) overrides ``geometry.angles``.
    """
    a = check_angles(angles, geometry)
    vol = check_volume(volume, geometry)
    out = JosephProjector(geometry).forward(mi.Float(vol.reshape(-1)), a)
    return mi.TensorXf(out, shape=(a.size, *geometry.nDetector))


def forward_project(volume, geometry: Geometry, angles=None) -> np.ndarray:
    """Joseph forward projection: float32 numpy [view, v, u] (density x length)."""
    # copy: .numpy() may be a view of Dr.Jit memory that is freed with the tensor
    return np.array(forward_project_dr(volume, geometry, angles).numpy(), copy=True)


def back_project_dr(proj, geometry: Geometry, angles=None) -> "mi.TensorXf":
    """Exact adjoint of ``forward_project``: [view, v, u] -> ``mi.TensorXf`` [x, y, z]."""
    a = check_angles(angles, geometry)
    p = check_projections(proj, geometry, a)
    out = JosephProjector(geometry).adjoint(mi.Float(p.reshape(-1)), a)
    return mi.TensorXf(out, shape=tuple(geometry.nVoxel))


def back_project(proj, geometry: Geometry, angles=None) -> np.ndarray:
    """Exact adjoint A^T of ``forward_project``: float32 numpy [x, y, z].

    Args:
        proj: [view, v, u] = (len(angles), *nDetector) values on detector pixels.
    """
    return np.array(back_project_dr(proj, geometry, angles).numpy(), copy=True)
