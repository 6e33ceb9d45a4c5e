"""The ``gaussian_medium`` plugin: radiative Gaussians as a purely absorbing Mitsuba medium.

sigma_t(x) = scale * sum_i rho_i exp(-1/2 m_i(x)^2) [m_i(x) <= extent], evaluated directly
(no voxel grid), albedo 0. Mitsuba's ``volpath`` then estimates exp(-line integral) by delta
tracking, an independent check of the closed-form projector (``mi_grg.evaluation.crosscheck``).
"""
from __future__ import annotations

import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np


def _inverse_covariances64(scales, q):
    """Sigma^-1 = R diag(1/s^2) R^T in float64 NumPy [N, 3, 3] (q = w, x, y, z, unit)."""
    w, x, y, z = q.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                 -1).reshape(-1, 3, 3)
    return np.einsum("nik,nk,njk->nij", R, 1.0 / np.square(scales), R), R


def majorant_bound(positions, scales, rotations, densities, extent, bbox_lo, bbox_hi,
                   grid: int = 48) -> float:
    """A safe upper bound of sigma_t over the box [bbox_lo, bbox_hi] (1/length).

    The smaller of (a) sum_i rho_i and (b) the voxelised field's maximum over a ``grid``^3
    lattice of cell centres covering the box, plus the Lipschitz bound of the untruncated
    field over half a cell diagonal (|grad G_i| <= rho_i / (s_min,i sqrt(e))), plus the
    truncation jumps sum_i rho_i exp(-extent^2/2), plus float32 slack."""
    rho = np.asarray(densities, np.float64)
    total = float(rho.sum())
    if total == 0.0:
        return 0.0
    from mi_grg.core.gaussians import Gaussians
    from mi_grg.core.geometry import Geometry
    from mi_grg.core.voxelizer import voxelize
    lo, hi = np.asarray(bbox_lo, np.float64), np.asarray(bbox_hi, np.float64)
    size = np.maximum(hi - lo, 1e-9)
    # a throw-away geometry: only its voxel grid matters to the voxelizer
    r = 0.5 * float(np.linalg.norm(size)) + float(np.linalg.norm(0.5 * (lo + hi)))
    geo = Geometry(mode="parallel", DSD=2 * r + 2, DSO=r + 1, nDetector=(1, 1),
                   sDetector=(1.0, 1.0), nVoxel=(grid,) * 3, sVoxel=size,
                   offOrigin=0.5 * (lo + hi), angles=[0.0])
    g = Gaussians.from_numpy(positions, scales, rotations, rho)
    peak = float(voxelize(g, geo, extent=extent).max())
    lipschitz = float(np.sum(rho / (np.min(scales, axis=1) * math.sqrt(math.e))))
    half_diag = 0.5 * float(np.linalg.norm(size / grid))
    bound = peak + lipschitz * half_diag + total * math.exp(-0.5 * extent * extent)
    return min(total, bound + 1e-5 * total) * (1 + 1e-5)


class GaussianMedium(mi.Medium):
    r"""
    .. _medium-gaussian_medium:

    Radiative Gaussians medium (:monosp:`gaussian_medium`)
    ------------------------------------------------------

    A purely absorbing heterogeneous medium whose extinction is a sum of anisotropic 3-D
    Gaussians, evaluated directly at every lookup (cost O(N) per lookup: meant for
    cross-checks with up to a few thousand Gaussians).

    .. pluginparameters::

     * - filename
       - |string|
       - Gaussians as a ``.npz`` (``mi_grg.core.gaussians.Gaussians.save_npz``: positions [N, 3],
         scales [N, 3] (length), rotations [N, 4] (w, x, y, z), densities [N] (1/length)).
     * - extent
       - |float|
       - Truncation radius in Mahalanobis units (default: the voxelizer's
         ``DEFAULT_EXTENT``); a Gaussian contributes where m <= extent.
     * - scale
       - |float|
       - Multiplies all densities, e.g. a unit conversion (default: 1).

    Extinction is spectrally flat, the albedo is 0 (``sigma_s = 0``), so ``volpath``
    computes transmittance only. ``get_majorant`` returns one global bound
    (``majorant_bound``); ``intersect_aabb`` the union of the Gaussians' ellipsoid boxes.
    Attach it as the ``interior`` of a shape with a ``null`` BSDF enclosing that box.
    Python attributes: ``majorant`` (float), ``bbox`` (mi.ScalarBoundingBox3f), ``n``.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        from mi_grg.core.gaussians import Gaussians
        from mi_grg.core.voxelizer import DEFAULT_EXTENT
        if "filename" not in props:
            raise ValueError("gaussian_medium needs 'filename' (a Gaussians .npz)")
        name = str(props["filename"])
        path = mi.file_resolver().resolve(name)   # relative: the scene's folder, cwd, ...
        if not os.path.exists(str(path)):
            raise FileNotFoundError(f"gaussian_medium: Gaussians file {name!r} not found "
                                    f"(searched the file resolver's folders)")
        self.filename = str(path)
        self.extent = float(props.get("extent", DEFAULT_EXTENT))
        if not (math.isfinite(self.extent) and self.extent > 0):
            raise ValueError(f"gaussian_medium: extent must be finite and > 0 "
                             f"(Mahalanobis units), got {self.extent}")
        scale = float(props.get("scale", 1.0))
        if not (math.isfinite(scale) and scale >= 0):
            raise ValueError(f"gaussian_medium: scale must be finite and >= 0, got {scale}")
        self.m_is_homogeneous = False
        self.m_has_spectral_extinction = False
        g = Gaussians.load_npz(self.filename).numpy()   # validated
        pos = g["positions"].astype(np.float64)
        sc = g["scales"].astype(np.float64)
        q = g["rotations"].astype(np.float64)
        rho = g["densities"].astype(np.float64) * scale
        self.n = len(rho)
        A, R = _inverse_covariances64(sc, q)
        half = self.extent * np.sqrt(np.einsum("nij,nj->ni", R * R, sc * sc))
        if self.n:
            lo, hi = (pos - half).min(0), (pos + half).max(0)
        else:
            lo = hi = np.zeros(3)
        self.bbox = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(*lo), mi.ScalarPoint3f(*hi))
        self.majorant = majorant_bound(pos, sc, q, rho, self.extent, lo, hi) if self.n else 0.0
        F = mi.Float
        self._p = [F(pos[:, k]) for k in range(3)]
        self._a = [F(A[:, i, j]) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
        self._rho = F(rho)
        dr.make_opaque(self._p, self._a, self._rho)

    def sigma_t(self, p):
        """sum_i rho_i exp(-m_i^2/2) [m_i <= extent] at points p (mi.Point3f), 1/length."""
        F, U = mi.Float, mi.UInt32
        if self.n == 0:
            return dr.zeros(F, dr.width(p))
        ext2 = dr.opaque(F, self.extent * self.extent)
        n = dr.opaque(U, self.n)
        P, A, rho = self._p, self._a, self._rho

        def body(i, acc):
            dx = p.x - dr.gather(F, P[0], i)
            dy = p.y - dr.gather(F, P[1], i)
            dz = p.z - dr.gather(F, P[2], i)
            a00, a01, a02, a11, a12, a22 = (dr.gather(F, c, i) for c in A)
            m2 = (dx * (a00 * dx + 2 * (a01 * dy + a02 * dz)) + dy * (a11 * dy + 2 * a12 * dz)
                  + a22 * dz * dz)
            # m2 <= extent^2 keeps exp's argument far above float32 underflow
            e = dr.select(m2 <= ext2, dr.exp(-0.5 * dr.minimum(m2, ext2)), 0.0)
            return i + 1, acc + dr.gather(F, rho, i) * e

        _, acc = dr.while_loop((U(0), dr.zeros(F, dr.width(p))), lambda i, acc: i < n, body,
                               label="gaussian_medium_sum")
        return acc

    def get_majorant(self, mei, active=True):
        return mi.UnpolarizedSpectrum(self.majorant)

    def get_scattering_coefficients(self, mei, active=True):
        st = dr.select(active, self.sigma_t(mei.p), 0.0)
        sigma_t = mi.UnpolarizedSpectrum(st)
        sigma_n = mi.UnpolarizedSpectrum(dr.maximum(self.majorant - st, 0.0))
        return mi.UnpolarizedSpectrum(0.0), sigma_n, sigma_t

    def intersect_aabb(self, ray):
        bb = mi.BoundingBox3f(self.bbox.min, self.bbox.max)
        hit, mint, maxt = bb.ray_intersect(ray)
        return hit, mint, maxt

    def traverse(self, callback):
        pass  # nothing differentiable: this medium is a reference, not an optimisation target

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        return (f"GaussianMedium[filename={self.filename!r}, n={self.n}, extent={self.extent}, "
                f"majorant={self.majorant:.6g}, bbox={self.bbox}]")


mi.register_medium("gaussian_medium", lambda props: GaussianMedium(props))
_registered_variant = mi.variant()
