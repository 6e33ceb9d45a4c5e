"""The ``ct_scanner`` sensor: every view of a circular CT scan as one Mitsuba sensor.

The film is the stack of all projections: ``views * nv`` rows by ``nu`` columns, so the
rendered image reshapes to [view, v, u]. Each film pixel shoots the ray of its detector
pixel centre (``Geometry.rays``, the single ray formula of mi_grg).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.data.scene import check_field_names, parse_scanner_fields


class CTScanner(mi.Sensor):
    r"""
    .. _sensor-ct_scanner:

    CT scanner (:monosp:`ct_scanner`)
    ---------------------------------

    A circular cone- or parallel-beam scan with TIGRE's field names; lengths in the unit of
    the scan, vectors as space-separated strings. Conventions: ``docs/conventions.md``.

    .. pluginparameters::

     * - mode
       - |string|
       - ``cone`` (rays from a point source) or ``parallel`` (rays along -(cos a, sin a, 0)).
     * - DSD, DSO
       - |float|
       - Source-detector and source-origin distances (length). Cone beam needs DSO < DSD.
     * - nDetector, sDetector
       - |string|
       - Detector pixels and size, ``"v u"`` (rows, columns; size of the whole detector).
     * - nVoxel, sVoxel
       - |string|
       - Volume voxels and size, ``"x y z"`` (size of the whole volume).
     * - offOrigin
       - |string|
       - Volume centre offset ``"x y z"`` (default: ``"0 0 0"``).
     * - offDetector
       - |string|
       - Detector centre offset ``"v u"`` along (e_v, e_u) (default: ``"0 0"``).
     * - views
       - |int|
       - Number of equally spaced training views (endpoint excluded). Or give ``angles``.
     * - total_angle, start_angle
       - |float|
       - Arc covered by ``views`` and its first angle, in DEGREES (default: 360, 0).
     * - angles
       - |string|
       - Explicit training angles in RADIANS, comma or space separated (instead of views).
     * - test_views
       - |int|
       - Held-out test views, half a step after the training grid over the same arc
         (default: 0). Or ``test_angles`` (radians).
     * - noise
       - |string|
       - ``none`` (default) or ``poisson+gaussian`` (training views only).
     * - I0, electronic_std
       - |float|
       - Photons per pixel (default: 1e4) and electronic noise std in counts (default: 10);
         only with ``noise=poisson+gaussian``.
     * - noise_seed
       - |int|
       - Seed of the noise draws (default: 0); only with ``noise=poisson+gaussian``.
     * - clip_negative
       - |bool|
       - Set negative noisy line integrals to 0, as R2-Gaussian does (default: true);
         only with ``noise=poisson+gaussian``.

    The plugin makes its own film (``hdrfilm``, luminance, box filter) of height
    ``views * nDetector[0]`` and width ``nDetector[1]``: view ``k`` fills rows
    ``k*nv .. (k+1)*nv - 1``. Rays go through pixel centres (every sample of a pixel
    gives the same ray), carry weight 1 and end behind both the detector and the volume's
    bounding sphere. Unknown or misspelled parameters raise an error.

    Film positions arrive in float32: in ``mi.render`` a jittered sample within about
    ``height * 1e-7`` pixels of a row edge can get the neighbouring row's ray (Mitsuba
    itself rounds such a sample onto the edge). Integrators that need every ray exact
    trace ``film_positions()`` (pixel centres) instead.

    Python attributes: ``geometry`` (``mi_grg.Geometry``, training angles), ``test_angles``
    (radians), ``noise`` (``None`` or a dict), ``to_projections(image)`` -> [view, v, u],
    ``film_positions()`` (pixel centres in film order).
    """

    def __init__(self, props: mi.Properties):
        T = mi.Properties.Type
        names = [k for k in props.keys() if props.type(k) not in (T.Object, T.ResolvedReference,
                                                                    T.Reference)]
        check_field_names(names)
        # Child objects: only the medium the rays start in (the scanned object). Our own
        # film replaces any other; a sampler would be a second place for spp and seed.
        media = []
        for k in props.keys():
            if k in names:
                continue
            obj = props[k]
            if not isinstance(obj, mi.Medium):
                raise ValueError(f"ct_scanner takes one child object, the <medium> it scans "
                                 f"(got {type(obj).__name__} {k!r}); it makes its own film, "
                                 "and mi.render takes spp and seed")
            media.append(obj)
        if len(media) > 1:
            raise ValueError(f"ct_scanner takes at most one <medium>, got {len(media)}")
        # Read only the fields present, so Mitsuba's own unreferenced-property check stays on.
        fields = {k: props[k] for k in names}
        self.geometry, self.test_angles, self.noise = parse_scanner_fields(fields)
        # A medium that needs the volume box (ct_phantom) takes it from the scan.
        place = getattr(media[0], "place", None) if media else None
        if place is not None:
            place(self.geometry)
        nv, nu = self.geometry.nDetector
        props["film"] = mi.load_dict({
            "type": "hdrfilm", "width": nu, "height": self.geometry.n_views * nv,
            "rfilter": {"type": "box"}, "pixel_format": "luminance"})
        super().__init__(props)
        # one row of 12 numbers per view (circular scans convert exactly): one sensor
        # frame per view
        self._tables = self.geometry.view_tables()
        g = self.geometry
        self._centre = [float(x) for x in g.offOrigin]
        self._radius = 0.5 * float(np.linalg.norm(g.sVoxel))

    @property
    def n_views(self) -> int:
        return self.geometry.n_views

    def to_projections(self, image) -> np.ndarray:
        """A rendered film image (``views * nv`` x ``nu``, any trailing channel of size 1)
        as a float32 NumPy array [view, v, u]."""
        arr = np.asarray(image, dtype=np.float32)
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[..., 0]
        nv, nu = self.geometry.nDetector
        if arr.shape != (self.n_views * nv, nu):
            raise ValueError(f"image must be [{self.n_views * nv}, {nu}] (views*v, u), "
                             f"got {arr.shape}")
        return arr.reshape(self.n_views, nv, nu)

    def film_positions(self):
        """Film positions (mi.Point2f in [0, 1)^2) of every pixel centre, in film order
        (row-major over ``views * nv`` rows and ``nu`` columns, i.e. [view, v, u]).

        ``sample_ray`` at these positions gives the rays of ``Geometry.pixel_rays_numpy``
        exactly; integrators that trace the whole film themselves should use them."""
        nv, nu = self.geometry.nDetector
        rows = self.n_views * nv
        idx = dr.arange(mi.UInt32, rows * nu)
        row = idx // nu
        col = idx - row * nu
        return mi.Point2f((mi.Float(col) + 0.5) / nu, (mi.Float(row) + 0.5) / rows)

    def sample_ray(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
        g = self.geometry
        nv, nu = g.nDetector
        rows = self.n_views * nv
        # film position -> (view, detector row, column); snap to the pixel centre
        col = dr.clip(mi.Int32(dr.floor(position_sample.x * nu)), 0, nu - 1)
        row = dr.clip(mi.Int32(dr.floor(position_sample.y * rows)), 0, rows - 1)
        view = row // nv
        v = mi.Float(row - view * nv) + 0.5
        u = mi.Float(col) + 0.5
        idx = mi.UInt32(view)
        (ox, oy, oz), (dx, dy, dz), length = g.rays_of_views(self._tables, idx, v, u, active)
        o = mi.Point3f(ox, oy, oz)
        d = mi.Vector3f(dx, dy, dz)
        # End behind the detector pixel and behind the volume's bounding sphere, whichever
        # is farther: the line integral of anything inside the volume is then complete.
        t_centre = dr.dot(mi.Point3f(*self._centre) - o, d)
        ray = mi.Ray3f(o, d, time, [])
        ray.maxt = dr.maximum(length, t_centre + self._radius)
        return ray, mi.Spectrum(1.0)

    def to_string(self):
        g = self.geometry
        return (f"CTScanner[mode={g.mode}, DSD={g.DSD}, DSO={g.DSO}, views={g.n_views}, "
                f"nDetector={list(g.nDetector)}, sDetector={list(g.sDetector)}, "
                f"offDetector={list(g.offDetector)}, test_views={len(self.test_angles)}, "
                f"noise={self.noise or 'none'}]")


mi.register_sensor("ct_scanner", lambda props: CTScanner(props))
_registered_variant = mi.variant()
