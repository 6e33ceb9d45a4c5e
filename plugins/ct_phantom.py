"""The ``ct_phantom`` medium: an analytic ellipsoid phantom as the object of a CT scene.

It names what is scanned (``mi_grg.data.phantoms.make_phantom``) and, as a pure absorber
whose extinction is the phantom's density, lets Mitsuba's own ``volpath`` render its
transmittance ``exp(-line integral)`` for cross-checks. It is placed by the
``ct_scanner`` sensor whose ``medium`` it is (``place(geometry)``), with the mapping of
``EllipsoidPhantom.world_transform``, so the scene states the volume box only once.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.data.phantoms import PHANTOMS, EllipsoidPhantom, make_phantom
from mi_grg.data.scene import ScanError, check_field_names, suggest

_FIELDS = {"phantom": "shepp | needles | shells | blobs", "seed": "random families only"}


class CTPhantom(mi.Medium):
    r"""
    .. _medium-ct_phantom:

    Analytic CT phantom (:monosp:`ct_phantom`)
    ------------------------------------------

    .. pluginparameters::

     * - phantom
       - |string|
       - ``shepp`` (3D modified Shepp-Logan), ``needles``, ``shells`` or ``blobs``.
     * - seed
       - |int|
       - Seed of the random families ``needles``, ``shells`` and ``blobs`` (default: 0). An error
         for ``shepp``, which has no randomness.

    Extinction sigma_t(p) = phantom density at p (1 / length), albedo 0. Give it as the
    ``medium`` of a ``ct_scanner`` sensor: the sensor places it in the volume box
    (``offOrigin + min(sVoxel)/2 * normalised``). An unplaced phantom raises on use.
    """

    def __init__(self, props: mi.Properties):
        T = mi.Properties.Type
        names = [k for k in props.keys() if props.type(k) not in (T.Object, T.ResolvedReference,
                                                                    T.Reference)]
        check_field_names(names, _FIELDS, where="ct_phantom")
        if "phantom" not in names:
            raise ScanError(f"ct_phantom needs a string 'phantom' (one of {PHANTOMS})")
        name = props["phantom"]
        if name not in PHANTOMS:
            raise ScanError(f"ct_phantom: unknown phantom {name!r}{suggest(str(name), PHANTOMS)}"
                            f"; valid: {', '.join(PHANTOMS)}")
        if name == "shepp" and "seed" in names:
            raise ScanError("ct_phantom: 'seed' has no effect on phantom 'shepp'; remove it")
        seed = props.get("seed", 0)
        if isinstance(seed, bool) or not float(seed).is_integer() or seed < 0:
            raise ScanError(f"ct_phantom: seed must be an integer >= 0, got {seed!r}")
        self.seed = int(seed)
        self.name = name
        self.phantom: EllipsoidPhantom = make_phantom(name, seed=self.seed)
        super().__init__(props)
        self.m_is_homogeneous = False
        self.m_has_spectral_extinction = False
        rho = self.phantom.densities
        # sum of the positive densities bounds the density everywhere (a valid majorant)
        self._majorant = float(np.clip(rho, 0, None).sum())
        self._ellipsoids = None
        self._box = None

    def description(self) -> dict:
        """What the scene file says: ``{"type": "ct_phantom", "phantom": ..., ["seed": ...]}``."""
        d = {"type": "ct_phantom", "phantom": self.name}
        if self.name != "shepp":
            d["seed"] = self.seed
        return d

    def place(self, geometry) -> None:
        """Map the phantom into ``geometry``'s volume box (called by ``ct_scanner``)."""
        origin, scale = EllipsoidPhantom.world_transform(geometry)
        # point p is inside ellipsoid k iff |(p - centre_k) @ M_k|^2 <= 1 (world units)
        self._ellipsoids = [
            ([float(x) for x in origin + scale * c], (np.asarray(b) / scale).tolist(), float(r))
            for c, b, r in zip(self.phantom.centres, self.phantom.frames(),
                               self.phantom.densities)]
        self._box = (origin - scale, origin + scale)

    def _check_placed(self):
        if self._ellipsoids is None:
            raise RuntimeError("ct_phantom is not placed: give it as the <medium> of a "
                               "ct_scanner sensor, which places it in the volume box")

    def density(self, p, active=True):
        """Phantom density at world points ``p`` (mi.Point3f) -> mi.Float (>= 0)."""
        self._check_placed()
        total = mi.Float(0.0)
        for c, m, rho in self._ellipsoids:  # few ellipsoids (<= tens): unrolled
            dx, dy, dz = p.x - c[0], p.y - c[1], p.z - c[2]
            q = [dx * m[0][j] + dy * m[1][j] + dz * m[2][j] for j in range(3)]
            inside = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= 1.0
            total += dr.select(inside, rho, 0.0)
        # cancelling densities (1 - 0.8 - 0.2) leave float32 round-off below 0
        return dr.maximum(total, 0.0)

    def intersect_aabb(self, ray):
        self._check_placed()
        lo, hi = self._box
        return mi.BoundingBox3f(mi.ScalarPoint3f(*lo), mi.ScalarPoint3f(*hi)).ray_intersect(ray)

    def get_majorant(self, mei, active=True):
        return mi.UnpolarizedSpectrum(self._majorant)

    def get_scattering_coefficients(self, mei, active=True):
        sigma_t = dr.minimum(self.density(mei.p, active), self._majorant)
        sigma_s = mi.UnpolarizedSpectrum(0.0)
        sigma_n = mi.UnpolarizedSpectrum(self._majorant - sigma_t)
        return sigma_s, sigma_n, mi.UnpolarizedSpectrum(sigma_t)

    def to_string(self):
        return f"CTPhantom[phantom={self.name}, seed={self.seed}, placed={self._box is not None}]"


mi.register_medium("ct_phantom", lambda props: CTPhantom(props))
_registered_variant = mi.variant()
