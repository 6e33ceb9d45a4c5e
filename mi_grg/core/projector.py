"""Radiative-Gaussian X-ray projector: exact line integrals of 3-D Gaussians, in Dr.Jit.

Model (``mi_grg.core.gaussians``): sigma(x) = sum_i rho_i exp(-1/2 (x - p_i)^T Sigma_i^-1 (x - p_i)).
The projection of pixel (view, v, u) is the line integral of sigma along that pixel's TRUE
ray (cone beam: from the source through the pixel centre; parallel beam: the whole line
through the pixel centre along the beam), in the geometry's length unit (density x length,
the unit of stored projections). Per Gaussian and ray the integral is closed form:

    rho sqrt(2 pi / a) exp(-m^2 / 2),  a = d^T Sigma^-1 d,  m^2 = c - b^2 / a,

(``m`` is the Mahalanobis distance between the line and the centre). No EWA/affine
approximation: ``a`` and ``m`` are evaluated exactly on every pixel's ray.

Truncation. Gaussian i contributes to a pixel only where m <= ``extent`` (E). The
projected 2-D Gaussian loses the mass fraction exp(-E^2/2) and each pixel at most
peak * exp(-E^2/2). ``DEFAULT_EXTENT`` = 4.5: exp(-E^2/2) = 4.0e-5 (< 1e-4 with room for
the sum over overlapping Gaussians). E = 3 (3DGS / R2-Gaussian's cut) costs 1.1e-2, E = 4
3.4e-4; the work per Gaussian grows as E^2 (see ``docs/bench/projector.md``).

Cancellation-safe evaluation (float32). Per (Gaussian, view) "record" everything is
expressed in the view frame (e_n towards the detector, e_u, e_v) relative to the source,
and in pixel offsets (du, dv) from the Gaussian's projected centre. With X = p - source,
Delta q = du e_u |E_u| + dv e_v |E_v| and r = q - source the (unnormalised) ray direction,

    m^2 = (Delta q x X)^T Sigma (Delta q x X) / (det Sigma . r^T Sigma^-1 r)

(because r x X = Delta q x X exactly). Both forms are written as sums of squares of
2x2 triangular factors whose entries come from covariance-form sums (Cauchy-Binet / adjugate
identities), never as differences of large quadratic forms, so needles (scale ratio 1e-4)
and far-from-origin scenes keep float32 accuracy.

Half-line (cone beam). A cone-beam ray starts at the source. A record is *regular* when its
whole E-ellipsoid lies in front of the source plane (so the footprint is a bounded
ellipse) and the source is >= sqrt(E^2 + 64) Mahalanobis units from the centre: then every
footprint ray reaches the closest point >= 8 units after the source and the whole-line
integral equals the half-line one to 1 - Phi(8) = 6e-16. Otherwise (Gaussian straddling,
touching or behind the source) the record is *near*: it is evaluated on the whole detector
with the exact half-line form  rho sqrt(2 pi / a) exp(-m^2/2) Phi(s),  s the signed
Mahalanobis distance from the source to the closest point. A record whose E-ellipsoid lies
entirely behind the source plane cannot reach any detector ray's half-line within E and is
dropped. Parallel beam integrates whole lines.

Work distribution (Gaussian-centric). Each regular record gets its exact footprint, the
ellipse {pixels whose ray meets the E-ellipsoid} (computed from the dual conic), split into
detector rows; each (record, row) is one SIMD lane that loops over the row's exact pixel
interval, evaluates the closed form and scatter-adds into the [view, v, u] image. The
backward pass loops over the same pixels, gathers the image gradient and accumulates the
gradient of the record's 11 parameters in registers (no per-pixel atomics); Dr.Jit AD then
carries those to the Gaussians. Memory stays bounded by chunking records and rows. On the
LLVM backend (``lanes.use_packets``) a lane writes its row ``PACKET`` pixels per contiguous
packet store, adds its gradient sums to its record with one packet store and reads its
record with one packet load (a SIMD scatter-add resolves lane conflicts one lane at a time
on the CPU); internal images then pad their rows to a whole number of packets.

Per-view scans: views whose detector values (distance, offsets, pixel steps, shear)
differ are projected in runs of equal values (``ViewFrames.groups``); a circular scan is
one run. A skewed detector (rows sheared against columns) keeps the frame orthonormal and
takes the closed form in the sheared pixel coordinates (``DetectorConstants.to_pixels``).

Where it lives: ``view_frames`` (detector frames from the ray formula),
``projector_inputs`` (checks, ``ProjectorError``), ``projector_records`` (the closed form
per record and its footprint), ``projector_kernels`` (the pixel loops, per-record sums),
``projector_chunks`` (chunks, classification, row batches), ``lanes`` (packets and lane
expansion, shared with the voxelizer); this module holds the differentiable operation.

API: ``project_dr`` (differentiable, mi.TensorXf [view, v, u]), ``project`` (NumPy float32
[view, v, u]), ``DEFAULT_EXTENT``, ``view_frames``. Rotations are normalised internally
(the rotation gradient is tangent to the unit sphere); given quaternions must be unit to
1e-3. ``means2d`` gradients are in pixel units (multiply by n/2 for 3DGS's NDC units).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry
from mi_grg.core.lanes import PACKET
from mi_grg.core.projector_chunks import (PreparedChunk, RowCapacity, expand_rows, plan_chunks,
                                          view_base)
from mi_grg.core.projector_inputs import ProjectorError, validate
from mi_grg.core.projector_kernels import RecordSums, near_kernel, regular_kernel
from mi_grg.core.projector_records import (DetectorConstants, RecordFrame, ViewFrameArrays,
                                           gaussian_arrays, near_params, regular_params)
from mi_grg.core.view_frames import ViewFrames, view_frames

__all__ = ["DEFAULT_EXTENT", "PACKET", "ProjectorError", "ViewFrames", "prepare", "project",
           "project_dr", "project_prepared", "view_frames"]

DEFAULT_EXTENT = 4.5
# Work sizes, read at call time (tests shrink them to exercise chunking and batching)
RECORDS_PER_CHUNK = 1 << 20   # (Gaussian, view) records evaluated at once
ROWS_PER_BATCH = 1 << 22      # (record, row) lanes launched at once
PIXELS_PER_CHUNK = 1 << 24    # image floats per chunk (ReduceMode.Expand copies it per thread)
_INPUT_NAMES = ("positions", "scales", "rotations", "densities", "density_scale", "means2d")


class _ProjectionSetup:
    """Static configuration of one projection (a plain object: not a PyTree)."""

    def __init__(self, geometry, views, det, n, nviews):
        self.geometry, self.views, self.det, self.n, self.nviews = geometry, views, det, n, nviews


class _ProjectOp(dr.CustomOp):
    """Differentiable projection; inputs are the Gaussians' arrays (see project_dr)."""

    def eval(self, positions, scales, rotations, densities, density_scale, means2d, setup):
        self.inputs = (positions, scales, rotations, densities, density_scale, means2d)
        self.setup = setup
        gauss = gaussian_arrays(Gaussians(positions, scales, rotations, densities), density_scale)
        return self._strided(self._by_chunk(gauss, means2d, dr.ADMode.Primal), crop=True)

    def _strided(self, image, crop: bool):
        """[view, v, u] image <-> internal layout (rows ``det.stride`` floats apart)."""
        det, nviews = self.setup.det, self.setup.nviews
        if det.stride_py == det.nu_py:
            return image
        flat = dr.arange(mi.UInt32, nviews * det.nv_py * det.nu_py)
        rows = flat // det.nu_py
        idx = rows * det.stride_py + (flat - rows * det.nu_py)
        if crop:
            return dr.gather(mi.Float, image, idx)
        out = dr.zeros(mi.Float, nviews * det.npix_py)
        dr.scatter(out, image, idx)
        return out

    def _by_chunk(self, gauss, means2d, mode, tangent_src=None):
        """Primal or tangent image: each chunk scatters into an image of its own views only
        (small targets keep ReduceMode.Expand cheap), then adds it into the full image."""
        det, nviews = self.setup.det, self.setup.nviews
        image = dr.zeros(mi.Float, nviews * det.npix_py)
        for prep in self._chunks(gauss, means2d):
            if prep.v0 == 0 and prep.v1 == nviews:
                self._run(prep, gauss, means2d, mode, image, tangent_src=tangent_src)
                continue
            part = dr.zeros(mi.Float, (prep.v1 - prep.v0) * det.npix_py)
            self._run(prep, gauss, means2d, mode, part, tangent_src=tangent_src)
            idx = dr.arange(mi.UInt32, dr.width(part)) + prep.v0 * det.npix_py
            dr.scatter_add(image, part, idx)
            dr.eval(image)
        dr.eval(image)
        return image

    # ---------------------------------------------------------------- helpers
    def _chunks(self, gauss, means2d):
        """Prepared chunks; a single chunk (the common training case) is kept from the
        primal pass for the derivative passes (it depends only on the primal inputs)."""
        setup = self.setup
        cached = getattr(self, "_single", None)
        if cached is not None:
            yield cached
            return
        plan = list(plan_chunks(setup.n, setup.nviews, setup.det.npix_py, RECORDS_PER_CHUNK,
                                PIXELS_PER_CHUNK))
        for v0, v1, g0, g1 in plan:
            prep = PreparedChunk(gauss, setup.views, setup.det, v0, v1, g0, g1, means2d, setup.n,
                                 caps=getattr(setup, "caps", None))
            if len(plan) == 1:
                self._single = prep
            yield prep

    def _record_params(self, gauss, means2d, prep, which):
        setup = self.setup
        det = setup.det
        gi, vi = (prep.reg_gi, prep.reg_vi) if which == "reg" else (prep.near_gi, prep.near_vi)
        frame = RecordFrame(gauss, setup.views, det, gi, vi, means2d, setup.n)
        return regular_params(frame, det) if which == "reg" else near_params(frame)

    def _run(self, prep, gauss, means2d, mode, image, gimage=None, tangent_src=None):
        """Runs one chunk. Returns per-record gradients (backward) as dicts."""
        out = {}
        if prep.n_reg:
            sums = self._run_regular(prep, mode, image, gimage, tangent_src)
            if mode == dr.ADMode.Backward:
                out["reg"] = sums
        if prep.n_near:
            sums = self._run_near(prep, gauss, means2d, mode, image, gimage, tangent_src)
            if mode == dr.ADMode.Backward:
                out["near"] = sums
        return out

    def _run_regular(self, prep, mode, image, gimage, tangent_src):
        """The regular records' kernels over their row batches; per-record gradient sums
        (backward) or None."""
        det = self.setup.det
        arrays = (prep.params, prep.footprint, prep.packed)
        tan = None
        if mode == dr.ADMode.Forward:
            tan = tangent_src(prep, "reg")
        v0 = 0 if mode == dr.ADMode.Backward else prep.v0
        one_view = prep.reg_gi is None          # the records are one view's Gaussians
        vbase = view_base(prep.reg_vi, det, v0, view=prep.v0 if one_view else None)
        return _sweep_rows(
            mode, prep.row_batches(ROWS_PER_BATCH), image, prep.params, prep.n_reg,
            lambda rec, row, valid=None: regular_kernel(mode, det, arrays, vbase, rec, row,
                                                        image, gimage, tan, valid))

    def _run_near(self, prep, gauss, means2d, mode, image, gimage, tangent_src):
        """The near-source records' kernels over every detector row; per-record gradient
        sums (backward) or None."""
        det = self.setup.det
        with dr.suspend_grad():
            params = self._record_params(gauss, means2d, prep, "near")
            dr.eval(params)
        tan = tangent_src(prep, "near") if mode == dr.ADMode.Forward else None
        vbase = view_base(prep.near_vi, det, 0 if mode == dr.ADMode.Backward else prep.v0)
        if prep.caps is not None:     # a recorded step: device lanes, empty slots masked
            batches = prep.near_lanes(det.nv_py)
        else:
            n_rows = np.full(prep.n_near, det.nv_py, np.uint32)
            batches = expand_rows(n_rows, dr.zeros(mi.Int32, prep.n_near), ROWS_PER_BATCH)
        return _sweep_rows(
            mode, batches, image, params, prep.n_near,
            lambda rec, row, valid=None: near_kernel(mode, det, params, vbase, rec, row, image,
                                                     gimage, tan, valid))

    def _leaves(self):
        """Fresh differentiable copies of the inputs (for AD inside backward/forward)."""
        leaves = []
        for x in self.inputs:
            if x is None:
                leaves.append(None)
                continue
            y = type(x)(x)
            dr.enable_grad(y)
            leaves.append(y)
        return leaves

    # ---------------------------------------------------------------- derivatives
    def backward(self):
        gimage = self.grad_out()
        if dr.width(gimage) == 0:
            return
        gimage = self._strided(mi.Float(gimage), crop=False)
        dr.eval(gimage)
        leaves = self._leaves()
        with dr.suspend_grad():
            gauss0 = _gaussian_arrays_of(self.inputs)
        for prep in self._chunks(gauss0, self.inputs[5]):
            grads = self._run(prep, gauss0, self.inputs[5], dr.ADMode.Backward, None, gimage)
            if grads:
                self._backward_to_leaves(prep, grads, leaves)
        for name, leaf in zip(_INPUT_NAMES, leaves):
            if leaf is not None:
                self.set_grad_in(name, dr.grad(leaf))

    def _backward_to_leaves(self, prep, grads, leaves):
        """Dr.Jit AD from one chunk's per-record parameter gradients to the Gaussians."""
        pos, sc, rot, den, dsc, md = leaves
        with dr.resume_grad():
            gauss = gaussian_arrays(Gaussians(pos, sc, rot, den), dsc)
            for which, acc in grads.items():
                params = self._record_params(gauss, md, prep, which)
                live = [k for k, v in params.items() if dr.grad_enabled(v)]
                for k in live:
                    dr.set_grad(params[k], acc[k])
                dr.enqueue(dr.ADMode.Backward, *[params[k] for k in live])
            dr.traverse(dr.ADMode.Backward)

    def forward(self):
        leaves = self._leaves()
        for name, leaf in zip(_INPUT_NAMES, leaves):
            if leaf is not None:
                dr.set_grad(leaf, self.grad_in(name))
        pos, sc, rot, den, dsc, md = leaves
        with dr.suspend_grad():
            gauss0 = _gaussian_arrays_of(self.inputs)

        def tangent_src(prep, which):
            with dr.resume_grad():
                gauss = gaussian_arrays(Gaussians(pos, sc, rot, den), dsc)
                params = self._record_params(gauss, md, prep, which)
                live = [v for v in params.values() if dr.grad_enabled(v)]
                # keep the leaves' tangents for the next chunk (no ClearInput)
                dr.forward_to(*live, flags=dr.ADFlag.ClearEdges | dr.ADFlag.ClearInterior
                              | dr.ADFlag.AllowNoGrad)
                tan = {k: dr.grad(v) if dr.grad_enabled(v) else dr.zeros(mi.Float, dr.width(v))
                       for k, v in params.items()}
                dr.eval(tan)
                return tan

        self.set_grad_out(self._strided(
            self._by_chunk(gauss0, self.inputs[5], dr.ADMode.Forward, tangent_src), crop=True))

    def name(self):
        return "RGProjector"


def _gaussian_arrays_of(inputs):
    """``gaussian_arrays`` of the operation's inputs (positions .. density_scale)."""
    return gaussian_arrays(Gaussians(*inputs[:4]), inputs[4])


# ====================================================================== public API
def project_dr(gaussians: Gaussians, geometry: Geometry, angles=None, extent: float = DEFAULT_EXTENT,
               density_scale=None, means2d=None) -> "mi.TensorXf":
    """Differentiable projections of radiative Gaussians, TensorXf [view, v, u].

    Args:
        gaussians: ``Gaussians`` (positions/scales in the geometry's length unit; may carry
            AD-attached Dr.Jit arrays, e.g. from ``Gaussians.from_raw``).
        geometry: the scan; ``angles`` (radians, [view]) overrides ``geometry.angles``.
        extent: truncation radius E in Mahalanobis units of the projected 2-D Gaussian
            (a Gaussian contributes where m_perp <= E; per-pixel error <= peak exp(-E^2/2));
            None: ``DEFAULT_EXTENT``.
        density_scale: optional mi.Float [N]; effective density rho_i * density_scale_i
            (GR-Gaussian's graph-augmented field hook; differentiable).
        means2d: optional mi.Vector2f [views * N], view-major (index = view * N + i): a
            zero-valued offset, in pixels along (e_u, e_v) at the Gaussian's depth, that moves
            Gaussian i within the detector plane of that view only. After ``dr.backward``
            its gradient is the detector-plane positional gradient (3DGS's means2D).
    Returns:
        mi.TensorXf [view, v, u], line integrals (density x length).
    """
    if not isinstance(gaussians, Gaussians):
        raise ProjectorError("gaussians must be a mi_grg.core.gaussians.Gaussians, got "
                             f"{type(gaussians).__name__}")
    if not isinstance(geometry, Geometry):
        raise ProjectorError(f"geometry must be a mi_grg.Geometry, got {type(geometry).__name__}")
    if extent is None:
        extent = DEFAULT_EXTENT
    try:
        extent = float(extent)
    except (TypeError, ValueError):
        raise ProjectorError(f"extent must be a number (Mahalanobis units), got {extent!r}") from None
    if not (math.isfinite(extent) and extent > 0):
        raise ProjectorError(f"extent must be finite and > 0 (Mahalanobis units), got {extent}")
    if angles is not None:
        geometry = geometry.with_angles(angles)
    nviews = geometry.n_views
    nv, nu = geometry.nDetector
    n = len(gaussians)
    if n == 0:
        return mi.TensorXf(dr.zeros(mi.Float, nviews * nv * nu), shape=(nviews, nv, nu))
    if density_scale is not None and not isinstance(density_scale, mi.Float):
        density_scale = mi.Float(density_scale)
    validate(gaussians, n, density_scale, means2d, nviews)
    fr = view_frames(geometry)
    parts = []
    for v0, v1 in fr.groups():   # one run for a circular scan
        sub = fr if (v0, v1) == (0, nviews) else fr.select(slice(v0, v1))
        md = means2d if (means2d is None or sub is fr) else dr.gather(
            mi.Vector2f, means2d, dr.arange(mi.UInt32, v0 * n, v1 * n))
        parts.append(project_prepared(prepare(geometry, n, extent, frames=sub), gaussians,
                                      density_scale, md))
    flat = parts[0] if len(parts) == 1 else dr.concat(parts)
    return mi.TensorXf(flat, shape=(nviews, nv, nu))


def prepare(geometry: Geometry, n: int, extent: float = DEFAULT_EXTENT, view=None,
            frames=None, rows=None) -> _ProjectionSetup:
    """The setup of one projection of ``n`` Gaussians, as ``project_dr`` builds it, for a
    caller that projects the same scan again and again (a training step): ``view`` one
    view's frame arrays ({"e": 3 x 3, "o": 3 mi.Float}, and "det" where a per-view scan's
    detector values differ, ``DetectorConstants.override``; None: every view of
    ``frames``), ``frames`` the ViewFrames the views and detector constants come from
    (None: ``view_frames(geometry)``; one run of equal detector values,
    ``ViewFrames.groups``), ``rows`` (rows, near records): fixed lane capacities, a
    recorded step's (no host read; the counts stay on the device in ``setup.caps``)."""
    fr = view_frames(geometry) if frames is None else frames
    views = ViewFrameArrays(fr) if view is None else ViewFrameArrays.of(view["e"], view["o"])
    det = DetectorConstants(fr, geometry, float(extent))
    if view is not None and "det" in view:
        det.override(view["det"])
    setup = _ProjectionSetup(geometry, views, det, n, fr.e_n.shape[0] if view is None else 1)
    if rows is not None:
        setup.caps = RowCapacity(*rows)
    return setup


def project_prepared(setup: _ProjectionSetup, gaussians: Gaussians, density_scale=None,
                     means2d=None) -> "mi.Float":
    """The differentiable projection (flat [view, v, u]) of ``prepare``'s setup; no input
    checks (``project_dr`` has them, ``check`` here)."""
    g = gaussians
    if setup.n == 0:
        return dr.zeros(mi.Float, setup.nviews * int(np.prod(setup.geometry.nDetector)))
    return dr.custom(_ProjectOp, g.positions, g.scales, g.rotations, g.densities,
                     density_scale, means2d, setup)


def project(gaussians: Gaussians, geometry: Geometry, angles=None, extent: float = DEFAULT_EXTENT,
            density_scale=None) -> np.ndarray:
    """Projections [view, v, u] as float32 NumPy line integrals (geometry's length unit)."""
    with dr.suspend_grad():
        img = project_dr(gaussians, geometry, angles, extent, density_scale)
    return np.asarray(img.numpy(), np.float32).reshape(img.shape)


def _sweep_rows(mode, batches, image, params, n_records: int, kernel):
    """Run ``kernel(rec, row)`` over the (record, row) batches: backward adds each batch's
    per-record gradient sums and returns them; otherwise the image is evaluated per batch
    (so a batch's lanes never pile up in one trace) and None is returned."""
    sums = RecordSums(params, n_records) if mode == dr.ADMode.Backward else None
    for batch in batches:       # (rec, row) or, with a row capacity, (rec, row, valid)
        if len(batch) == 3:
            _masked_batch(batch, sums, kernel)
            dr.eval(image if sums is None else sums.acc)
            continue
        r = kernel(*batch)
        if sums is not None:
            sums.add(r, batch[0])
        else:
            dr.eval(image)
    return None if sums is None else sums.result()


def _masked_batch(batch, sums, kernel):
    """A row capacity's batch (rec, row, valid): the kernel and the backward's record sums
    inside a symbolic conditional on ``valid``. The lanes past the last row form the tail
    of the batch, so whole SIMD packets (LLVM) skip them rather than run their set-up
    masked; the kernel still masks the invalid lanes of a mixed packet."""
    rec, row, valid = batch

    def lanes(rec, row, valid):
        r = kernel(rec, row, valid)
        if sums is not None:
            sums.add(r, rec, evaluate=False)
        return ()

    dr.if_stmt((rec, row, valid), valid, lanes, lambda *_: (), mode="symbolic",
               label="capacity_lanes")
