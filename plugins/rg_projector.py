"""The ``rg_projector`` integrator: radiative-Gaussian X-ray projections as a Mitsuba integrator.

It renders, for a sensor that exposes a ``geometry`` (``ct_scanner``), the exact line
integrals of its Gaussians (``mi_grg.core.projector``) into the sensor's film layout
[views * nv, nu, 1]. Its Gaussian arrays are scene parameters, so ``mi.traverse``,
``mi.ad`` optimizers, ``mi.render(scene, params=...)`` and ``dr.backward`` work.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.projector import DEFAULT_EXTENT, ProjectorError, project_dr

_KEYS = ("positions", "scales", "rotations", "densities")


# Mitsuba's Python AD integrator base of the ACTIVE variant: this module is reloaded on
# every variant switch (the mitsuba.ad alias keeps the first variant's class)
from mitsuba.python.ad.integrators.common import ADIntegrator  # noqa: E402


class RGProjector(ADIntegrator):
    r"""
    .. _integrator-rg_projector:

    Radiative-Gaussian projector (:monosp:`rg_projector`)
    -----------------------------------------------------

    Line integrals of a sum of 3-D Gaussians along every detector pixel's ray of a CT
    sensor, in closed form (no sampling: ``spp`` and ``seed`` are ignored). The sensor must
    have a ``geometry`` attribute (a ``mi_grg.Geometry``) and a film of height
    ``views * nDetector[0]`` and width ``nDetector[1]``, like ``ct_scanner``.

    .. pluginparameters::

     * - extent
       - |float|
       - Truncation radius in Mahalanobis units of each projected Gaussian; per-pixel
         truncation error <= peak * exp(-extent^2/2). (Default: ``DEFAULT_EXTENT`` = 4.5)
     * - filename
       - |string|
       - Optional Gaussians ``.npz`` (``Gaussians.save_npz``). Without it the integrator
         holds zero Gaussians until its parameters are set.
     * - positions, scales, rotations, densities
       - |tensor|
       - Exposed parameters: positions [N, 3] (Point3f), scales [N, 3] (Vector3f, > 0),
         rotations [N, 4] (Vector4f, unit quaternions w, x, y, z), densities [N] (Float).
       - |exposed|, |differentiable|

    The rendered tensor has shape [views * nv, nu, 1]; ``sensor.to_projections`` turns it
    into [view, v, u]. Python attributes: ``gaussians()`` (a ``Gaussians`` view of the
    parameters), ``set_gaussians(g)``, ``density_scale`` (optional mi.Float [N]
    multiplying the densities, not a scene parameter).
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.extent = float(props.get("extent", DEFAULT_EXTENT))
        if not self.extent > 0:
            raise ValueError(f"rg_projector: extent must be > 0, got {self.extent}")
        filename = props.get("filename", "")
        if filename:
            g = Gaussians.load_npz(filename)
        else:   # zero Gaussians until the parameters are set
            g = Gaussians(positions=mi.Point3f(), scales=mi.Vector3f(),
                          rotations=mi.Vector4f(), densities=mi.Float())
        self.set_gaussians(g)
        self.density_scale = None

    # ------------------------------------------------------------------ parameters
    def set_gaussians(self, g: Gaussians) -> None:
        self.positions, self.scales = g.positions, g.scales
        self.rotations, self.densities = g.rotations, g.densities

    def gaussians(self) -> Gaussians:
        return Gaussians(positions=self.positions, scales=self.scales,
                         rotations=self.rotations, densities=self.densities)

    def traverse(self, callback):
        for k in _KEYS:
            callback.put(k, getattr(self, k), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        n = dr.width(self.densities)
        for k in _KEYS:
            if dr.width(getattr(self, k)) != n:
                raise ProjectorError(f"rg_projector: {k} has {dr.width(getattr(self, k))} "
                                     f"entries, densities has {n}")

    # ------------------------------------------------------------------ rendering
    def _sensor(self, scene, sensor):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        geo = getattr(sensor, "geometry", None)
        if geo is None:
            raise ValueError("rg_projector needs a CT sensor with a 'geometry' attribute "
                             f"(e.g. ct_scanner), got {type(sensor).__name__}")
        size = sensor.film().size()
        nv, nu = geo.nDetector
        if (int(size[0]), int(size[1])) != (nu, geo.n_views * nv):
            raise ValueError(f"rg_projector: film is {int(size[0])} x {int(size[1])}, expected "
                             f"{nu} x {geo.n_views * nv} (nu x views*nv)")
        return sensor, geo

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise Exception("rg_projector: develop=True must be specified")
        sensor, geo = self._sensor(scene, sensor)
        img = project_dr(self.gaussians(), geo, extent=self.extent,
                         density_scale=self.density_scale)
        nv, nu = geo.nDetector
        out = mi.TensorXf(img.array, shape=(geo.n_views * nv, nu, 1))
        if evaluate:
            dr.eval(out)
        return out

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            img = self.render(scene, sensor, seed, spp, True, False)
            dr.forward_to(img)
            return dr.grad(img)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            img = self.render(scene, sensor, seed, spp, True, False)
            dr.set_grad(img, grad_in)
            dr.enqueue(dr.ADMode.Backward, img)
            dr.traverse(dr.ADMode.Backward)

    def to_string(self):
        return f"RGProjector[extent={self.extent}, gaussians={dr.width(self.densities)}]"


mi.register_integrator("rg_projector", lambda props: RGProjector(props))
_registered_variant = mi.variant()
