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
LLVM backend (``_packets``) a lane writes its row ``PACKET`` pixels per contiguous packet
store, adds its gradient sums to its record with one packet store and reads its record
with one packet load (a SIMD scatter-add resolves lane conflicts one lane at a time on the
CPU); internal images then pad their rows to a whole number of packets.

API: ``project_dr`` (differentiable, mi.TensorXf [view, v, u]), ``project`` (NumPy float32
[view, v, u]), ``DEFAULT_EXTENT``, ``view_frames``. Rotations are normalised internally
(the rotation gradient is tangent to the unit sphere); given quaternions must be unit to
1e-3. ``means2d`` gradients are in pixel units (multiply by n/2 for 3DGS's NDC units).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.gaussians import QUATERNION_TOL, Gaussians, rotation_matrix
from mi_grg.core.geometry import Geometry

__all__ = ["DEFAULT_EXTENT", "ProjectorError", "ViewFrames", "project", "project_dr",
           "view_frames"]

DEFAULT_EXTENT = 4.5
HALF_LINE_MARGIN = 8.0        # Mahalanobis units between source and closest point (regular)
RECORDS_PER_CHUNK = 1 << 20   # (Gaussian, view) records evaluated at once
ROWS_PER_BATCH = 1 << 22      # (record, row) lanes launched at once
PIXELS_PER_CHUNK = 1 << 24    # image floats per chunk (ReduceMode.Expand copies it per thread)
_BOUND_PAD = 1e-3             # relative/absolute slack of the footprint (pixels)
_J_MIN = 0.05                 # smallest eigenvalue of the footprint's perspective factor J
PACKET = 4                    # pixels (voxels) per packet store on LLVM (see _packets)
_SQRT_2PI = math.sqrt(2.0 * math.pi)


_PROFILE = None   # a dict to collect phase times / counts (bench/projector.py); None: off


def _tick(name, count=None):
    """Profiling only: synchronise and book the time since the previous tick under name."""
    if _PROFILE is None:
        return
    import time
    dr.sync_thread()
    now = time.perf_counter()
    last = _PROFILE.get("_last", now)
    _PROFILE[name] = _PROFILE.get(name, 0.0) + (now - last)
    _PROFILE["_last"] = now
    if count is not None:
        for k, v in count.items():
            _PROFILE[k] = _PROFILE.get(k, 0) + v


class ProjectorError(ValueError):
    """Invalid projector input; the message names the argument."""


# ====================================================================== view frames
@dataclass(frozen=True)
class ViewFrames:
    """Per-view detector frames derived (in float64) from ``Geometry.rays``.

    Pixel (v, u) (continuous, centre of pixel (i, j) at (i + 0.5, j + 0.5)) lies at
    ``origin + h e_n + (a_u + u du) e_u + (a_v + v dv) e_v`` where ``origin`` is the source
    (cone) or the corner pixel's point (parallel, a_u = a_v = 0); parallel rays run along
    e_n. Arrays are [view, 3]; scalars are shared by all views."""
    cone: bool
    e_n: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    origin: np.ndarray
    h: float
    a_u: float
    a_v: float
    du: float
    dv: float


def view_frames(geometry: Geometry, angles=None) -> ViewFrames:
    """The detector frame of every view, read off ``geometry.rays`` (float64), so that the
    projector follows the one ray formula of mi_grg. Raises if the rays are not those of
    a planar detector with orthogonal axes and view-independent offsets."""
    a = geometry.angles if angles is None else np.asarray(angles, np.float64).reshape(-1)
    c, s = np.cos(a), np.sin(a)
    nv, nu = geometry.nDetector

    def at(v, u):
        o, d, length = geometry.rays(c, s, np.full_like(a, float(v)), np.full_like(a, float(u)))
        o = np.stack(np.broadcast_arrays(*o), -1)
        d = np.stack(np.broadcast_arrays(*d), -1)
        return o, d, o + np.asarray(length)[..., None] * d

    o00, d00, q00 = at(0, 0)
    o01, _, q01 = at(0, 1)
    o10, _, q10 = at(1, 0)
    _, _, qff = at(nv, nu)
    E_u, E_v = q01 - q00, q10 - q00
    du, dv = np.linalg.norm(E_u, axis=1), np.linalg.norm(E_v, axis=1)
    e_u, e_v = E_u / du[:, None], E_v / dv[:, None]
    scale = float(np.abs(q00).max() + 1.0)
    if not np.allclose(qff, q00 + nu * E_u + nv * E_v, rtol=0, atol=1e-9 * scale):
        raise ProjectorError("geometry.rays is not affine in the pixel coordinates "
                             "(planar detector expected)")
    if np.abs(np.sum(e_u * e_v, 1)).max() > 1e-9:
        raise ProjectorError("detector axes e_u, e_v are not orthogonal")
    cone = geometry.mode == "cone"
    if cone:
        if not (np.allclose(o00, o01, atol=1e-12 * scale) and np.allclose(o00, o10, atol=1e-12 * scale)):
            raise ProjectorError("cone-beam rays do not share one source point")
        origin = o00
        e_n = np.cross(e_u, e_v)
        rel = q00 - origin
        e_n *= np.sign(np.sum(rel * e_n, 1))[:, None]
        h = np.sum(rel * e_n, 1)
        a_u, a_v = np.sum(rel * e_u, 1), np.sum(rel * e_v, 1)
    else:
        e_n = d00
        if np.abs(np.sum(e_n * e_u, 1)).max() > 1e-9 or np.abs(np.sum(e_n * e_v, 1)).max() > 1e-9:
            raise ProjectorError("parallel-beam direction is not normal to the detector")
        origin = q00
        h = np.full_like(a, float(geometry.DSD))
        a_u = a_v = np.zeros_like(a)
    for name, arr in (("h", h), ("a_u", a_u), ("a_v", a_v), ("du", du), ("dv", dv)):
        if np.ptp(arr) > 1e-9 * (np.abs(arr).max() + scale):
            raise ProjectorError(f"detector frame value {name} differs between views")
    return ViewFrames(cone, e_n, e_u, e_v, origin, float(h[0]), float(a_u[0]), float(a_v[0]),
                      float(du[0]), float(dv[0]))


# ====================================================================== inputs
def _check_finite(name, arr, shape_txt):
    ok = dr.all(dr.isfinite(arr), axis=None) if dr.width(arr) else True
    if not bool(ok):
        raise ProjectorError(f"{name} {shape_txt} contains NaN or Inf")


def unit_quaternions(q):
    """q / |q| (differentiable). Used by the projector and the voxelizer, so that the
    rotation gradient is tangent to the unit sphere and R(q) is a rotation exactly."""
    return q * dr.rsqrt(dr.squared_norm(q))


def gaussian_checks(g: Gaussians, density_scale=None) -> list:
    """Per-Gaussian validity tests shared by the projector and the voxelizer, in reporting
    order: [(bad lanes, message)]. Lazy; ``first_failure`` evaluates them all at once.
    Widths must already agree (density_scale included)."""
    p, s, q, rho = (dr.detach(a) for a in (g.positions, g.scales, g.rotations, g.densities))

    def nonfinite(*comps):
        bad = ~dr.isfinite(comps[0])
        for c in comps[1:]:
            bad |= ~dr.isfinite(c)
        return bad

    qn = dr.squared_norm(q)
    checks = [
        (nonfinite(p.x, p.y, p.z), "gaussians.positions [N, 3] contains NaN or Inf"),
        (nonfinite(s.x, s.y, s.z), "gaussians.scales [N, 3] contains NaN or Inf"),
        (nonfinite(q.x, q.y, q.z, q.w), "gaussians.rotations [N, 4] (w, x, y, z) contains NaN or Inf"),
        (nonfinite(rho), "gaussians.densities [N] contains NaN or Inf"),
        (dr.minimum(dr.minimum(s.x, s.y), s.z) <= 0,
         "gaussians.scales must be > 0 (standard deviations, length unit)"),
        (rho < 0, "gaussians.densities must be >= 0"),
        (qn == 0, "gaussians.rotations contains a zero quaternion (w, x, y, z)"),
        (dr.abs(dr.sqrt(qn) - 1) > QUATERNION_TOL,
         f"gaussians.rotations must be unit quaternions (w, x, y, z), | |q| - 1 | <= "
         f"{QUATERNION_TOL}; unnormalised quaternions given (normalise them first)"),
    ]
    if density_scale is not None:
        checks.append((nonfinite(dr.detach(density_scale)), "density_scale [N] contains NaN or Inf"))
    return checks


def first_failure(g: Gaussians, checks: list):
    """The message of the first check (in list order) that fails for any Gaussian, or None.

    One kernel and one host synchronisation for all checks (this runs on every training
    iteration): each lane's first failing check index, min-reduced over the lanes. The
    Gaussians' own arrays are evaluated by the same kernel, so later kernels reuse them."""
    code = mi.UInt32(len(checks))
    for k in reversed(range(len(checks))):
        code = dr.select(checks[k][0], k, code)
    dr.schedule(dr.detach(g.positions), dr.detach(g.scales), dr.detach(g.rotations),
                dr.detach(g.densities))
    k = int(dr.min(code)[0])
    return checks[k][1] if k < len(checks) else None


def _validate(g: Gaussians, n: int, density_scale, means2d, n_views: int):
    for name, arr, k in (("positions", g.positions, 3), ("scales", g.scales, 3),
                         ("rotations", g.rotations, 4)):
        if len(arr) != k:
            raise ProjectorError(f"gaussians.{name} must have {k} components, got {len(arr)}")
        for comp in arr:
            if dr.width(comp) != n:
                raise ProjectorError(f"gaussians.{name} has {dr.width(comp)} entries, densities has {n}")
    if density_scale is not None and dr.width(density_scale) != n:
        raise ProjectorError(f"density_scale must have shape [N] = [{n}], got {dr.width(density_scale)}")
    msg = first_failure(g, gaussian_checks(g, density_scale))
    if msg is not None:
        raise ProjectorError(msg)
    if means2d is not None:
        if len(means2d) != 2 or dr.width(means2d) != n * n_views:
            raise ProjectorError(f"means2d must be a Vector2f of N * views = {n * n_views} entries "
                                 f"(view-major: index = view * N + gaussian), got {dr.width(means2d)}")
        _check_finite("means2d", dr.detach(means2d), "[views * N, 2]")


# ====================================================================== records
class _DetectorConstants:
    """Geometry scalars as opaque Dr.Jit values (one compiled kernel for all geometries)."""

    def __init__(self, fr: ViewFrames, geometry: Geometry, extent: float):
        F = mi.Float
        nv, nu = geometry.nDetector
        self.cone = fr.cone
        self.nu_py, self.nv_py = nu, nv
        # Internal images store rows ``stride`` floats apart: nu rounded up to a whole
        # number of packets where the primal pass writes packets (cropped on the way out)
        stride = -(-nu // PACKET) * PACKET if _packets() else nu
        self.stride_py = stride
        self.stride = dr.opaque(mi.Int32, stride)
        self.h = dr.opaque(F, fr.h)
        self.h2 = dr.opaque(F, fr.h * fr.h)
        self.a_u, self.a_v = dr.opaque(F, fr.a_u), dr.opaque(F, fr.a_v)
        self.du, self.dv = dr.opaque(F, fr.du), dr.opaque(F, fr.dv)
        self.E = dr.opaque(F, extent)
        self.E2 = dr.opaque(F, extent * extent)
        self.Eb2 = dr.opaque(F, (extent * (1 + _BOUND_PAD)) ** 2)
        self.margin2 = dr.opaque(F, extent * extent + HALF_LINE_MARGIN ** 2)
        self.nu, self.nv = dr.opaque(mi.Int32, nu), dr.opaque(mi.Int32, nv)
        self.nuf, self.nvf = dr.opaque(F, float(nu)), dr.opaque(F, float(nv))
        self.npix = dr.opaque(mi.UInt32, stride * nv)
        self.npix_py = stride * nv      # floats per view of an internal image


class _ViewFrameArrays:
    """Per-view frame vectors as Dr.Jit arrays (float32), indexed by global view id."""

    def __init__(self, fr: ViewFrames):
        self.e = [[_to_dr(mi.Float, axis[:, k]) for k in range(3)] for axis in (fr.e_n, fr.e_u, fr.e_v)]
        # origin coordinates in the view frame, in float64 before rounding
        self.o = [_to_dr(mi.Float, np.sum(fr.origin * axis, 1)) for axis in (fr.e_n, fr.e_u, fr.e_v)]


def _to_dr(T, a):
    """NumPy -> Dr.Jit array, padded to >= 2 entries: width-1 host arrays become scalar kernel
    inputs whose load alignment follows the (varying) address, which defeats the kernel cache."""
    a = np.asarray(a)
    dtype = {mi.Float: np.float32, mi.UInt32: np.uint32, mi.Int32: np.int32}[T]
    if a.size < 2:
        a = np.concatenate([a.reshape(-1), np.zeros(2 - a.size)])
    return T(np.ascontiguousarray(a, dtype))


def _gaussian_arrays(g: Gaussians, density_scale):
    """Per-Gaussian Dr.Jit quantities shared by all views (differentiable).

    Rotations are normalised here (as ``Gaussians.from_raw`` does), so that Sigma^-1 =
    R S^-2 R^T = Sigma^-1 of ``gaussians.inverse_covariance`` holds exactly and the rotation
    gradient is tangent to the unit sphere."""
    R = rotation_matrix(unit_quaternions(g.rotations))
    rho = g.densities if density_scale is None else g.densities * density_scale
    return {"p": [g.positions.x, g.positions.y, g.positions.z],
            "s": [g.scales.x, g.scales.y, g.scales.z],
            "R": [[R[i][j] for j in range(3)] for i in range(3)], "rho": rho}


class _RecordFrame:
    """Quantities of a set of records (Gaussian index gi, view index vi) in the view frame,
    lengths divided by sigma = max scale (detached) so that every record is O(1)."""

    def __init__(self, gauss, views: _ViewFrameArrays, det: _DetectorConstants, gi, vi,
                 means2d=None, n_gauss=0):
        F = mi.Float
        # ReduceMode.Local: the adjoint scatter-add then carries no array-size literal
        # (Auto would pick Expand, whose kernels are recompiled whenever N changes)
        loc = dr.ReduceMode.Local
        if gi is None:   # every Gaussian once, in order: no gathers (nor adjoint scatters)
            gather = lambda a: a  # noqa: E731
        else:
            gather = lambda a: dr.gather(F, a, gi, mode=loc)  # noqa: E731
        gather_view = lambda a: dr.gather(F, a, vi)  # noqa: E731
        p = [gather(a) for a in gauss["p"]]
        s = [gather(a) for a in gauss["s"]]
        R = [[gather(gauss["R"][i][j]) for j in range(3)] for i in range(3)]
        self.rho = gather(gauss["rho"])
        E = [[gather_view(views.e[axis][k]) for k in range(3)] for axis in range(3)]
        O = [gather_view(views.o[axis]) for axis in range(3)]
        # X = p - origin in frame coordinates (n, u, v)
        X = [p[0] * E[axis][0] + p[1] * E[axis][1] + p[2] * E[axis][2] - O[axis] for axis in range(3)]
        if means2d is not None:
            # zero-valued detector-plane shift, in pixels at the Gaussian's depth
            md = means2d if gi is None else dr.gather(
                mi.Vector2f, means2d, vi * dr.opaque(mi.UInt32, n_gauss) + gi, mode=loc)
            depth = dr.detach(X[0]) / det.h if det.cone else 1.0
            X[1] = X[1] + md.x * det.du * depth
            X[2] = X[2] + md.y * det.dv * depth
        # Gaussian axes in the frame: Rf[axis][l] = e_axis . R[:, l]
        Rf = [[E[axis][0] * R[0][l] + E[axis][1] * R[1][l] + E[axis][2] * R[2][l] for l in range(3)]
              for axis in range(3)]
        sig = dr.detach(dr.maximum(dr.maximum(s[0], s[1]), s[2]))
        isig = 1.0 / sig
        self.sig, self.isig = sig, isig
        self.sn = [sk * isig for sk in s]          # normalised scales in (0, 1]
        self.Xn = [x * isig for x in X]            # X / sigma
        self.X = X
        self.Rf = Rf


def _sigma_entry(frame, i, j):
    """Sigma'_{ij} (normalised) = sum_l s_l^2 Rf_il Rf_jl."""
    return sum(dr.square(frame.sn[l]) * frame.Rf[i][l] * frame.Rf[j][l] for l in range(3))


def _ghat2(frame):
    """|g|^2 = X^T Sigma^-1 X (Mahalanobis distance source-centre, squared)."""
    acc = 0
    for l in range(3):
        gl = frame.Rf[0][l] * frame.Xn[0] + frame.Rf[1][l] * frame.Xn[1] + frame.Rf[2][l] * frame.Xn[2]
        acc = acc + dr.square(gl / frame.sn[l])
    return acc


def _regular_params(frame: _RecordFrame, det: _DetectorConstants):
    """The 11 per-record parameters of the regular closed form (differentiable).

    Pixel (u, v) (continuous), du = u - uc, dv = v - vc:
        y1 = N11 du + N21 dv, y2 = N22 dv,  num = y1^2 + y2^2
        pu = du - su, pv = dv - sv, z1 = D11 pu + D21 pv, z2 = D22 pv, den = 1 + z1^2 + z2^2
        m^2 = num / den,  value = amp * L(u, v) / sqrt(den) * exp(-m^2 / 2)
    with L the source-pixel distance (cone; parallel: den = L = 1)."""
    sn, Rf, Xn = frame.sn, frame.Rf, frame.Xn
    S_nn, S_nu, S_nv = _sigma_entry(frame, 0, 0), _sigma_entry(frame, 0, 1), _sigma_entry(frame, 0, 2)
    det_s = dr.square(sn[0] * sn[1] * sn[2])
    dun, dvn = det.du * frame.isig, det.dv * frame.isig     # pixel steps / sigma
    if det.cone:
        xn, xu, xv = Xn
        lam = det.h / frame.X[0]
        uc = (lam * frame.X[1] - det.a_u) / det.du
        vc = (lam * frame.X[2] - det.a_v) / det.dv
        # numerator: (Dq x X)^T Sigma (Dq x X) = Delta^T Wn Delta, t_l = s_l R_l^T w
        tu = [sn[l] * (Rf[0][l] * xv - Rf[2][l] * xn) for l in range(3)]
        tv = [sn[l] * (Rf[1][l] * xn - Rf[0][l] * xu) for l in range(3)]
        w_uu = dr.square(dun) * sum(t * t for t in tu)
        w_uv = dun * dvn * sum(tu[l] * tv[l] for l in range(3))
        n11r = dr.sqrt(w_uu)
        ghat = dr.sqrt(_ghat2(frame))
        sdet = sn[0] * sn[1] * sn[2]
        beta = (det.h * frame.isig) * dr.rsqrt(S_nn)        # beta^2 = min over pixels of r^T A r
        N11 = n11r / (sdet * beta)
        N21 = w_uv / (n11r * sdet * beta)
        N22 = dun * dvn * xn * ghat / (n11r * beta)   # sqrt(det Wn) = du dv sdet xn |g|
        # denominator: r^T A r = beta^2 (1 + |Dc (Delta - Delta*)|^2)
        A_uu = sum(dr.square(Rf[1][l] / sn[l]) for l in range(3))
        A_uv = sum(Rf[1][l] * Rf[2][l] / dr.square(sn[l]) for l in range(3))
        ra = dr.rsqrt(A_uu)
        D11 = dun * A_uu * ra / beta
        D21 = dvn * A_uv * ra / beta
        D22 = dvn * dr.sqrt(S_nn / det_s) * ra / beta   # det(A_uv block) = Sigma_nn / det Sigma
        su = -lam * (frame.X[1] - frame.X[0] * S_nu / S_nn) / det.du
        sv = -lam * (frame.X[2] - frame.X[0] * S_nv / S_nn) / det.dv
        amp = frame.rho * (_SQRT_2PI * frame.sig) * dr.sqrt(S_nn) / det.h
        return dict(uc=uc, vc=vc, N11=N11, N21=N21, N22=N22, D11=D11, D21=D21, D22=D22,
                    su=su, sv=sv, amp=amp)
    # parallel: m^2 = Delta_phys^T Sigma_uv^-1 Delta_phys, value = rho sqrt(2 pi / A_nn) e^(-m^2/2)
    S_uu, S_uv, S_vv = _sigma_entry(frame, 1, 1), _sigma_entry(frame, 1, 2), _sigma_entry(frame, 2, 2)
    A_nn = sum(dr.square(Rf[0][l] / sn[l]) for l in range(3))
    det_uv = det_s * A_nn                            # det of Sigma's (u, v) block
    r_vv = dr.rsqrt(S_vv)
    rd = dr.rsqrt(det_uv)
    return dict(uc=frame.X[1] / det.du, vc=frame.X[2] / det.dv,
                N11=dun * dr.sqrt(S_vv) * rd, N21=-dvn * S_uv * r_vv * rd, N22=dvn * r_vv,
                amp=frame.rho * (_SQRT_2PI * frame.sig) * dr.rsqrt(A_nn))


_REGULAR_PARAMS_CONE = ("uc", "vc", "N11", "N21", "N22", "D11", "D21", "D22", "su", "sv", "amp")
_REGULAR_PARAMS_PARALLEL = ("uc", "vc", "N11", "N21", "N22", "amp")
_NEAR_PARAMS = ("M00", "M01", "M02", "M10", "M11", "M12", "M20", "M21", "M22", "g0", "g1", "g2", "amp")


def _near_params(frame: _RecordFrame):
    """Near-source records: whitening rows M_l = Rf[:, l] / s_l (frame coords), g = M X,
    amp = rho sqrt(2 pi) sigma. Value = amp L / |M r| exp(-m^2/2) Phi(s) (see kernel)."""
    out = {}
    g = []
    for l in range(3):
        inv = 1.0 / frame.sn[l]
        for k in range(3):
            out[f"M{l}{k}"] = frame.Rf[k][l] * inv
        g.append((frame.Rf[0][l] * frame.Xn[0] + frame.Rf[1][l] * frame.Xn[1]
                  + frame.Rf[2][l] * frame.Xn[2]) * inv)
    out.update(g0=g[0], g1=g[1], g2=g[2], amp=frame.rho * (_SQRT_2PI * frame.sig))
    return out


def _footprint(params, det: _DetectorConstants):
    """Exact footprint ellipse of regular records (detached): {m^2 <= E^2} in pixel offsets
    from (uc, vc) is (Delta - c)^T S^-1 (Delta - c) <= 1. Returns row range and per-row
    interval coefficients, plus a mask of well-conditioned ellipses."""
    N11, N21, N22 = params["N11"], params["N21"], params["N22"]
    Eb2 = det.Eb2
    p11, p22 = 1.0 / N11, 1.0 / N22
    p12 = -N21 * p11 * p22                      # P = Nc^-1 (upper triangular)
    if det.cone:
        D11, D21, D22 = params["D11"], params["D21"], params["D22"]
        # B = Dc P (upper triangular), J = I - E^2 B^T B
        b11, b12, b22 = D11 * p11, D11 * p12 + D21 * p22, D22 * p22
        J11 = 1 - Eb2 * b11 * b11
        J12 = -Eb2 * b11 * b12
        J22 = 1 - Eb2 * (b12 * b12 + b22 * b22)
        detJ = J11 * J22 - J12 * J12
        half_tr = 0.5 * (J11 + J22)
        lam_min = half_tr - dr.sqrt(dr.maximum(dr.square(0.5 * (J11 - J22)) + J12 * J12, 0))
        ok = lam_min >= _J_MIN
        idet = 1.0 / detJ
        Ji11, Ji12, Ji22 = J22 * idet, -J12 * idet, J11 * idet
        w1 = D11 * params["su"] + D21 * params["sv"]          # w = Dc Delta*
        w2 = D22 * params["sv"]
        bw1, bw2 = b11 * w1, b12 * w1 + b22 * w2      # B^T w
        jb1 = Ji11 * bw1 + Ji12 * bw2
        jb2 = Ji12 * bw1 + Ji22 * bw2                 # J^-1 B^T w
        cu = -Eb2 * (p11 * jb1 + p12 * jb2)
        cv = -Eb2 * (p22 * jb2)
        k = Eb2 * Eb2 * (bw1 * jb1 + bw2 * jb2) + Eb2 * (1 + w1 * w1 + w2 * w2)
    else:
        Ji11, Ji12, Ji22 = 1.0, 0.0, 1.0
        detJ = 1.0
        ok = dr.isfinite(N11) & dr.isfinite(N21) & dr.isfinite(N22)
        cu = cv = dr.zeros(mi.Float, dr.width(N11))
        k = Eb2
    # S = k P J^-1 P^T
    q1 = Ji11 * p11 + Ji12 * p12
    q2 = Ji12 * p11 + Ji22 * p12
    S_uu = k * (p11 * q1 + p12 * q2)
    S_uv = k * (q2 * p22)
    S_vv = k * Ji22 * p22 * p22
    det_S = k * k / (detJ * dr.square(N11 * N22))
    # row range and u range (bounding box) in continuous pixel coordinates
    rv = dr.sqrt(dr.maximum(S_vv, 0)) * (1 + _BOUND_PAD) + _BOUND_PAD
    ru = dr.sqrt(dr.maximum(S_uu, 0)) * (1 + _BOUND_PAD) + _BOUND_PAD
    vcen = params["vc"] + cv
    ucen = params["uc"] + cu
    row_lo = dr.ceil(dr.clip(vcen - rv - 0.5, -1.0, det.nvf))
    row_hi = dr.floor(dr.clip(vcen + rv - 0.5, -1.0, det.nvf))
    row_lo = dr.maximum(row_lo, 0.0)
    row_hi = dr.minimum(row_hi, det.nvf - 1)
    u_in = (ucen + ru > 0) & (ucen - ru < det.nuf)
    n_rows = dr.select(ok & u_in & (row_hi >= row_lo), row_hi - row_lo + 1, 0.0)
    return dict(ok=ok, row_lo=mi.Int32(row_lo), n_rows=mi.UInt32(n_rows), cu=cu, cv=cv,
                slope=S_uv / S_vv, hw2=det_S / dr.square(S_vv), S_vv=S_vv)


# ====================================================================== kernels
def _scatter_mode():
    return dr.ReduceMode.Expand if dr.backend_v(mi.Float) == dr.JitBackend.LLVM else dr.ReduceMode.Auto


def _packets() -> bool:
    """Whether the kernels use packet loads and stores (the LLVM backend).

    On the CPU a per-pixel ``scatter_add`` resolves conflicts between the SIMD lanes one
    lane at a time; it was ~60 % of the primal pass, and the backward's eleven per-record
    scatter-adds ~30 % of its kernel. With packets, a lane evaluates its row ``PACKET``
    pixels at a time and adds them with one contiguous store, the backward adds a lane's
    sums to its record with one contiguous store, and each lane reads its record with one
    packet load (docs/benchmarks.md, "Training step"). CUDA keeps the per-pixel atomics,
    which it executes natively."""
    return dr.backend_v(mi.Float) == dr.JitBackend.LLVM


_FOOTPRINT_KEYS = ("cu", "cv", "slope", "hw2", "S_vv")   # a footprint row's pixel interval
_RECORD_WIDTH = 16          # floats per packed record (parameters + footprint, padded)
_EXPAND_BYTES = 1 << 29     # largest per-thread copy of a packet-store target


def expand_fits(n_floats: int) -> bool:
    """Whether ReduceMode.Expand's per-thread copies of an ``n_floats`` target stay within
    ``_EXPAND_BYTES`` (the packet stores' condition, with ``_packets()``)."""
    return n_floats * 4 * dr.thread_count() <= _EXPAND_BYTES


def pack_rows(vals: list, width: int):
    """Per-row values (``len(vals) <= width`` arrays of one width n) as one row-major
    [n, width] array (lazy), which a lane reads with one packet load
    (``dr.gather(mi.ArrayXf, packed, row, shape=(width, lanes))``)."""
    n = dr.width(vals[0])
    vals = list(vals) + [dr.zeros(mi.Float, n)] * (width - len(vals))
    packed = dr.zeros(mi.Float, n * width)
    dr.scatter(packed, mi.ArrayXf(vals), dr.arange(mi.UInt32, n))
    return packed


def _param_keys(det):
    return _REGULAR_PARAMS_CONE if det.cone else _REGULAR_PARAMS_PARALLEL


def _record_keys(det):
    return _param_keys(det) + _FOOTPRINT_KEYS


def _pack_records(det, params, footprint):
    """The records' parameters and footprint values as one [record, 16] array
    (``pack_rows``); None off the LLVM backend."""
    if not _packets():
        return None
    return pack_rows([params[k] for k in _param_keys(det)]
                     + [footprint[k] for k in _FOOTPRINT_KEYS], _RECORD_WIDTH)


def _row_bounds(det, uc, dv, t):
    """Pixel columns [lo, hi] (Int32, clamped) of a footprint row; dv = row centre - vc,
    ``t`` holds the record's footprint values (``_FOOTPRINT_KEYS``)."""
    I32 = mi.Int32
    y = dv - t["cv"]
    hw = (dr.sqrt(dr.maximum(t["hw2"] * (t["S_vv"] - y * y), 0)) * (1 + _BOUND_PAD)
          + _BOUND_PAD)
    ucr = uc + t["cu"] + t["slope"] * y
    lo = I32(dr.maximum(dr.ceil(dr.clip(ucr - hw - 0.5, -1.0, det.nuf)), 0.0))
    hi = I32(dr.minimum(dr.floor(dr.clip(ucr + hw - 0.5, -1.0, det.nuf)), det.nuf - 1))
    return lo, hi


def _row_interval(det, uc, dv, footprint, rec):
    """``_row_bounds`` of lanes ``rec`` (gathers the footprint values)."""
    return _row_bounds(det, uc, dv, {k: dr.gather(mi.Float, footprint[k], rec)
                                     for k in _FOOTPRINT_KEYS})


def _lane_values(det, params, footprint, packed, rec, row):
    """Per (record, row) lane: the record's values (dict), the row centre v, dv = v - vc and
    the row's pixel interval [lo, hi]. One packet load per lane where ``packed`` exists."""
    keys = _record_keys(det)
    if packed is not None:
        pk = dr.gather(mi.ArrayXf, packed, rec, shape=(_RECORD_WIDTH, dr.width(rec)))
        t = {k: pk[i] for i, k in enumerate(keys)}
    else:
        src = {**params, **footprint}
        t = {k: dr.gather(mi.Float, src[k], rec) for k in keys}
    v = mi.Float(row) + 0.5
    dv = v - t["vc"]
    lo, hi = _row_bounds(det, t["uc"], dv, t)
    return t, v, dv, lo, hi


def _lane_base(vbase, rec):
    """Flat index of pixel (0, 0) of each lane's view: ``vbase`` is an opaque Int32 when
    every record is in the same view, else a per-record UInt32 array."""
    return vbase if isinstance(vbase, mi.Int32) and dr.width(vbase) == 1 \
        else mi.Int32(dr.gather(mi.UInt32, vbase, rec))


def _regular_kernel(mode, det, prep_arrays, vbase, rec, row, image, gimage=None, tan=None):
    """One lane per (record, detector row); loops over the row's footprint pixels.

    ``prep_arrays`` = (params, footprint, packed) of the records. Mode
    ``dr.ADMode.Primal``: add the values into ``image`` (rows ``det.stride`` apart; on LLVM
    ``PACKET`` pixels per store); ``Backward``: return the gradient of <image, gimage>
    w.r.t. the 11 (6 parallel) record parameters per lane; ``Forward``: scatter-add the
    tangent given the parameter tangents ``tan``."""
    F, I32 = mi.Float, mi.Int32
    cone = det.cone
    params, footprint, packed = prep_arrays
    t, v, dv, lo, hi = _lane_values(det, params, footprint, packed, rec, row)
    uc, vc, N11, N21, N22, amp = t["uc"], t["vc"], t["N11"], t["N21"], t["N22"], t["amp"]
    pix0 = _lane_base(vbase, rec) + row * det.stride
    c1 = N21 * dv
    y2 = N22 * dv
    y2sq = y2 * y2
    if cone:
        D11, D21, D22 = t["D11"], t["D21"], t["D22"]
        pv = dv - t["sv"]
        c2 = D21 * pv - D11 * t["su"]
        z2 = D22 * pv
        z2p1 = 1 + z2 * z2
        sv_len = det.a_v + v * det.dv
        h2sv2 = det.h2 + sv_len * sv_len
    if mode == dr.ADMode.Forward:
        tt = {k: dr.gather(F, tan[k], rec) for k in _param_keys(det)}
    smode = _scatter_mode()

    def pixel(u):
        du = u - uc
        y1 = dr.fma(N11, du, c1)
        num = dr.fma(y1, y1, y2sq)
        if cone:
            z1 = dr.fma(D11, du, c2)
            den = dr.fma(z1, z1, z2p1)
            su_len = dr.fma(u, det.du, det.a_u)
            # L / sqrt(den) = sqrt(L^2 / den): one reciprocal and one square root per pixel
            inv_den = dr.rcp(den)
            m2 = num * inv_den
            L_rs = dr.sqrt(dr.fma(su_len, su_len, h2sv2) * inv_den)
            base0 = L_rs * dr.exp(-0.5 * dr.minimum(m2, det.E2))
            return du, y1, num, z1, den, inv_den, m2, base0
        m2 = num
        base0 = dr.exp(-0.5 * dr.minimum(m2, det.E2))
        return du, y1, num, None, None, None, m2, base0

    if mode == dr.ADMode.Primal and _packets():
        # PACKET-aligned blocks of the row; pixels outside [lo, hi] (or the footprint) add 0.
        # pix0 is a multiple of PACKET (det.stride is), so block = pix0 / PACKET + b.
        W = PACKET
        blk0 = mi.UInt32(pix0) // W

        def body(b):
            j0 = b * W
            u0 = F(j0) + 0.5
            vals = []
            for k in range(W):
                m2, base0 = pixel(u0 + k)[-2:]
                act = (m2 <= det.E2) & (j0 + k >= lo) & (j0 + k <= hi)
                vals.append(dr.select(act, amp * base0, 0.0))
            dr.scatter_add(image, mi.ArrayXf(vals), blk0 + mi.UInt32(b), mode=dr.ReduceMode.Expand)
            return (b + 1,)
        dr.while_loop((lo // W,), lambda b: b <= hi // W, body, labels=("b",), label="rg_primal_packet")
        return None

    if mode == dr.ADMode.Primal:
        def body(j):
            m2, base0 = pixel(F(j) + 0.5)[-2:]
            dr.scatter_add(image, amp * base0, mi.UInt32(pix0 + j), active=m2 <= det.E2, mode=smode)
            return (j + 1,)
        dr.while_loop((lo,), lambda j: j <= hi, body, labels=("j",), label="rg_primal")
        return None

    if mode == dr.ADMode.Forward:
        def body(j):
            du, y1, num, z1, den, inv_den, m2, base0 = pixel(F(j) + 0.5)
            val = amp * base0
            # d num and d den from the parameter tangents
            dnum = 2 * y1 * (tt["N11"] * du + tt["N21"] * dv - N11 * tt["uc"] - N21 * tt["vc"]) \
                + 2 * y2 * (tt["N22"] * dv - N22 * tt["vc"])
            dval = base0 * tt["amp"]
            if cone:
                pu = du - t["su"]
                dden = 2 * z1 * (tt["D11"] * pu + tt["D21"] * pv - D11 * (tt["uc"] + tt["su"])
                                 - D21 * (tt["vc"] + tt["sv"])) \
                    + 2 * z2 * (tt["D22"] * pv - D22 * (tt["vc"] + tt["sv"]))
                dval = dval + val * 0.5 * inv_den * ((m2 - 1) * dden - dnum)
            else:
                dval = dval - 0.5 * val * dnum
            dr.scatter_add(image, dval, mi.UInt32(pix0 + j), active=m2 <= det.E2, mode=smode)
            return (j + 1,)
        dr.while_loop((lo,), lambda j: j <= hi, body, labels=("j",), label="rg_forward")
        return None

    # backward: accumulate the seven sums per lane
    zero = F(0)

    def body(j, Sa, Sy1du, Sy1, SN, Sz1pu, Sz1, SD):
        du, y1, num, z1, den, inv_den, m2, base0 = pixel(F(j) + 0.5)
        act = m2 <= det.E2
        g = dr.gather(F, gimage, mi.UInt32(pix0 + j), active=act)
        gb = g * base0
        gI = gb * amp
        Sa = Sa + gb
        if cone:
            tq = 0.5 * gI * inv_den
            gN = -tq
            gD = tq * (m2 - 1)
            pu = du - t["su"]
            Sz1pu = dr.fma(gD * z1, pu, Sz1pu)
            Sz1 = dr.fma(gD, z1, Sz1)
            SD = SD + gD
        else:
            gN = -0.5 * gI
        gy = gN * y1
        Sy1du = dr.fma(gy, du, Sy1du)
        Sy1 = Sy1 + gy
        SN = SN + gN
        return j + 1, Sa, Sy1du, Sy1, SN, Sz1pu, Sz1, SD

    state = (lo, zero, zero, zero, zero, zero, zero, zero)
    _, Sa, Sy1du, Sy1, SN, Sz1pu, Sz1, SD = dr.while_loop(
        state, lambda j, *a: j <= hi, body,
        labels=("j", "Sa", "Sy1du", "Sy1", "SN", "Sz1pu", "Sz1", "SD"), label="rg_backward")
    gr = dict(amp=Sa, N11=2 * Sy1du, N21=2 * dv * Sy1, N22=2 * y2 * dv * SN,
              uc=-2 * N11 * Sy1, vc=-2 * (N21 * Sy1 + N22 * y2 * SN))
    if cone:
        gr.update(D11=2 * Sz1pu, D21=2 * pv * Sz1, D22=2 * z2 * pv * SD,
                  su=-2 * D11 * Sz1, sv=-2 * (D21 * Sz1 + D22 * z2 * SD))
        gr["uc"] = gr["uc"] + gr["su"]
        gr["vc"] = gr["vc"] + gr["sv"]
    return gr


class _RecordSums:
    """Per-record sums of the backward's per-lane gradients, over one or more row batches.

    On LLVM (when the per-thread copies stay below ``_EXPAND_BYTES``) a lane adds its
    sums with one contiguous packet store into a [record, width] array; otherwise one
    scatter-add per parameter (reduced within a SIMD packet first)."""

    def __init__(self, keys, n):
        self.keys, self.n = tuple(keys), n
        self.width = 1 << max(len(self.keys) - 1, 0).bit_length()
        self.packed = _packets() and expand_fits(n * self.width)
        if self.packed:
            self.acc = dr.zeros(mi.Float, n * self.width)
        else:
            self.acc = {k: dr.zeros(mi.Float, n) for k in self.keys}

    def add(self, sums, rec):
        if self.packed:
            vals = [sums[k] for k in self.keys]
            vals += [dr.zeros(mi.Float, dr.width(rec))] * (self.width - len(vals))
            dr.scatter_add(self.acc, mi.ArrayXf(vals), rec, mode=dr.ReduceMode.Expand)
        else:
            for k in self.keys:
                dr.scatter_add(self.acc[k], sums[k], rec, mode=dr.ReduceMode.Local)
        dr.eval(self.acc)

    def result(self) -> dict:
        if not self.packed:
            return self.acc
        pk = dr.gather(mi.ArrayXf, self.acc, dr.arange(mi.UInt32, self.n),
                       shape=(self.width, self.n))
        out = {k: mi.Float(pk[i]) for i, k in enumerate(self.keys)}
        dr.eval(out)
        return out


def _phi(x):
    """Standard normal CDF (float32; erf form, exact enough for a multiplicative factor)."""
    return 0.5 * (1.0 + dr.erf(x * (1.0 / math.sqrt(2.0))))


def _near_kernel(mode, det, params, vbase, rec, row, image, gimage=None, tan=None):
    """One lane per (near record, detector row) over the whole row; exact half-line form."""
    F, I32 = mi.Float, mi.Int32
    gather = lambda a: dr.gather(F, a, rec)  # noqa: E731
    t = {k: gather(params[k]) for k in _NEAR_PARAMS}
    M = [[t[f"M{l}{k}"] for k in range(3)] for l in range(3)]
    gv = [t["g0"], t["g1"], t["g2"]]
    amp = t["amp"]
    v = F(row) + 0.5
    sv_len = det.a_v + v * det.dv
    h2sv2 = det.h2 + sv_len * sv_len
    kl = [M[l][0] * det.h + M[l][2] * sv_len for l in range(3)]   # row-constant part of M r
    pix0 = _lane_base(vbase, rec) + row * det.stride
    smode = _scatter_mode()
    if mode == dr.ADMode.Forward:
        tt = {k: gather(tan[k]) for k in _NEAR_PARAMS}

    def pixel(j):
        u = F(j) + 0.5
        su_len = dr.fma(u, det.du, det.a_u)
        L = dr.sqrt(dr.fma(su_len, su_len, h2sv2))
        D = [dr.fma(M[l][1], su_len, kl[l]) for l in range(3)]
        q = dr.maximum(D[0] * D[0] + D[1] * D[1] + D[2] * D[2], 1e-30)
        c = [D[1] * gv[2] - D[2] * gv[1], D[2] * gv[0] - D[0] * gv[2], D[0] * gv[1] - D[1] * gv[0]]
        pp = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        tdot = D[0] * gv[0] + D[1] * gv[1] + D[2] * gv[2]
        rq = dr.rsqrt(q)
        m2 = pp * rq * rq
        s = tdot * rq
        base0 = L * rq * dr.exp(-0.5 * dr.minimum(m2, det.E2))
        Phi = _phi(s)
        return su_len, D, q, c, rq, m2, s, base0, Phi

    def dI(D, q, c, rq, m2, s, base0, Phi):
        """Partials of I w.r.t. D (3), g (3) and amp, as (gD, gg, base0 * Phi)."""
        val = amp * base0 * Phi
        phi = dr.exp(-0.5 * dr.minimum(s * s, 174.0)) * (1.0 / _SQRT_2PI)
        iq = rq * rq
        Iq = 0.5 * iq * (val * (m2 - 1) - amp * base0 * phi * s)
        Ip = -0.5 * val * iq
        It = amp * base0 * phi * rq
        xc = [gv[1] * c[2] - gv[2] * c[1], gv[2] * c[0] - gv[0] * c[2], gv[0] * c[1] - gv[1] * c[0]]
        cd = [c[1] * D[2] - c[2] * D[1], c[2] * D[0] - c[0] * D[2], c[0] * D[1] - c[1] * D[0]]
        gD = [2 * D[l] * Iq + 2 * Ip * xc[l] + It * gv[l] for l in range(3)]
        gg = [2 * Ip * cd[l] + It * D[l] for l in range(3)]
        return gD, gg, base0 * Phi

    j0 = I32(0)
    last = det.nu - 1
    if mode == dr.ADMode.Primal:
        def body(j):
            _, _, _, _, _, m2, _, base0, Phi = pixel(j)
            dr.scatter_add(image, amp * base0 * Phi, mi.UInt32(pix0 + j), active=m2 <= det.E2, mode=smode)
            return (j + 1,)
        dr.while_loop((j0,), lambda j: j <= last, body, labels=("j",), label="rg_near_primal")
        return None
    if mode == dr.ADMode.Forward:
        def body(j):
            su_len, D, q, c, rq, m2, s, base0, Phi = pixel(j)
            gD, gg, bphi = dI(D, q, c, rq, m2, s, base0, Phi)
            dval = bphi * tt["amp"]
            for l in range(3):
                dD = tt[f"M{l}0"] * det.h + tt[f"M{l}1"] * su_len + tt[f"M{l}2"] * sv_len
                dval = dval + gD[l] * dD + gg[l] * tt[f"g{l}"]
            dr.scatter_add(image, dval, mi.UInt32(pix0 + j), active=m2 <= det.E2, mode=smode)
            return (j + 1,)
        dr.while_loop((j0,), lambda j: j <= last, body, labels=("j",), label="rg_near_forward")
        return None

    zero = F(0)

    def body(j, *acc):
        su_len, D, q, c, rq, m2, s, base0, Phi = pixel(j)
        act = m2 <= det.E2
        g = dr.gather(F, gimage, mi.UInt32(pix0 + j), active=act)
        gD, gg, bphi = dI(D, q, c, rq, m2, s, base0, Phi)
        acc = list(acc)
        for l in range(3):
            acc[l] = dr.fma(g, gD[l], acc[l])                  # sum g dI/dD_l
            acc[3 + l] = dr.fma(g * gD[l], su_len, acc[3 + l])  # sum g dI/dD_l su
            acc[6 + l] = dr.fma(g, gg[l], acc[6 + l])
        acc[9] = dr.fma(g, bphi, acc[9])
        return (j + 1, *acc)

    out = dr.while_loop((j0,) + (zero,) * 10, lambda j, *a: j <= last, body,
                        label="rg_near_backward")
    acc = out[1:]
    gr = {"amp": acc[9]}
    for l in range(3):
        gr[f"M{l}0"] = acc[l] * det.h
        gr[f"M{l}1"] = acc[3 + l]
        gr[f"M{l}2"] = acc[l] * sv_len
        gr[f"g{l}"] = acc[6 + l]
    return gr


# ====================================================================== chunk planning
def _expand_rows(n_rows_np: np.ndarray, row_lo, max_items: int):
    """Batches of at most ``max_items`` (record, row) lanes, yielded as (rec UInt32,
    row Int32); lanes of one record are consecutive (its rows in order)."""
    n = np.asarray(n_rows_np).astype(np.int64)
    if n.size == 0:
        return
    csum = np.cumsum(n)
    start = 0
    while start < n.size:
        base = int(csum[start - 1]) if start else 0
        end = max(int(np.searchsorted(csum, base + max_items, side="right")), start + 1)
        cnt = int(csum[end - 1]) - base
        if cnt > 0:
            sel = np.nonzero(n[start:end])[0] + start
            offs = (csum[sel] - n[sel] - base).astype(np.uint32)
            marker = dr.zeros(mi.UInt32, cnt)
            dr.scatter(marker, mi.UInt32(1), mi.UInt32(offs.astype(np.uint32)))
            k = dr.cumsum(marker) - 1                       # index among records with rows
            rec = dr.gather(mi.UInt32, _to_dr(mi.UInt32, sel), k)
            first = dr.gather(mi.UInt32, _to_dr(mi.UInt32, offs), k)
            row = mi.Int32(dr.arange(mi.UInt32, cnt) - first) + dr.gather(mi.Int32, row_lo, rec)
            dr.eval(rec, row)
            yield rec, row
        start = end


def segment_lanes(counts, skip: int, total: int):
    """Expand segments into lanes: for lane j in [0, total) its segment ``slot`` and its
    ``offset`` inside the segment (both mi.UInt32 [total]).

    Segment i holds ``counts[i]`` (mi.UInt32) items; the first ``skip`` items of segment 0
    are left out. An exclusive ``dr.prefix_sum`` gives each segment's first item; a marker
    per segment start and an inclusive prefix sum over the items give each item its
    segment (empty segments share their start with the next one and never win). Used for
    the projector's (record, row) lanes and the voxelizer's (Gaussian, column) lanes."""
    UInt32 = mi.UInt32
    first = dr.prefix_sum(counts)
    skip_u = dr.opaque(UInt32, skip)
    pos = first - skip_u                 # wraps for segment 0: masked by k > 0
    k = dr.arange(UInt32, dr.width(counts))
    marker = dr.zeros(UInt32, total)
    # total changes with every view and block: as a literal (in the comparison, or the
    # per-thread copies of the LLVM backend's default ReduceMode.Expand) it made a new
    # kernel, compiled at 6-8 ms, on every projection and TV block
    in_range = pos < dr.opaque(UInt32, total)
    dr.scatter_add(marker, UInt32(1), pos, active=(k > 0) & in_range, mode=dr.ReduceMode.Local)
    slot = dr.prefix_reduce(dr.ReduceOp.Add, marker, exclusive=False)
    offset = dr.arange(UInt32, total) + skip_u - dr.gather(UInt32, first, slot)
    return slot, offset


def _plan_chunks(n: int, n_views: int, npix: int):
    """(v0, v1, g0, g1) blocks of at most RECORDS_PER_CHUNK records and PIXELS_PER_CHUNK
    image floats (view-major)."""
    vmax = max(1, PIXELS_PER_CHUNK // npix)
    if n * n_views <= RECORDS_PER_CHUNK and n_views <= vmax:
        yield 0, n_views, 0, n
        return
    vpc = max(1, min(RECORDS_PER_CHUNK // n, vmax))
    gpc = min(n, RECORDS_PER_CHUNK)
    for v0 in range(0, n_views, vpc):
        for g0 in range(0, n, gpc):
            yield v0, min(n_views, v0 + vpc), g0, min(n, g0 + gpc)


class _Prepared:
    """Classification and footprints of one chunk (all detached)."""

    def __init__(self, gauss, views, det, v0, v1, g0, g1, means2d, n_gauss):
        U = mi.UInt32
        self.v0, self.v1 = v0, v1
        nvc, ngc = v1 - v0, g1 - g0
        # One view and every Gaussian (a training iteration): the records are the Gaussians
        # themselves, indexed directly (gi = None) and not compacted to the regular ones
        # (non-regular records get no rows).
        identity = (nvc == 1 and ngc == n_gauss
                    and (means2d is None or dr.width(means2d) == n_gauss))
        gi = None if identity else g0 + dr.tile(dr.arange(U, ngc), nvc)
        vi = v0 + dr.repeat(dr.arange(U, nvc), ngc)
        dr.eval(vi)   # keeps the sizes (literals) out of the big kernels below
        if gi is not None:
            dr.eval(gi)
        with dr.suspend_grad():
            frame = _RecordFrame(gauss, views, det, gi, vi, means2d, n_gauss)
            params = _regular_params(frame, det)
            footprint = _footprint(params, det)
            if det.cone:
                S_nn = _sigma_entry(frame, 0, 0)
                reach = frame.Xn[0] + det.E * dr.sqrt(S_nn)       # front-most depth of the E-ellipsoid
                regular = footprint["ok"] & (frame.Xn[0] > 0) & (_ghat2(frame) >= det.margin2)
                near = ~regular & (reach > 0)
            else:
                regular = footprint["ok"]
                near = None
            regular = regular & (footprint["n_rows"] > 0)
            footprint.pop("ok")
            if identity:
                footprint["n_rows"] = dr.select(regular, footprint["n_rows"], 0)
                self.params, self.footprint = params, footprint
                self.packed = _pack_records(det, params, footprint)
                dr.eval(params, footprint, near, self.packed)   # one kernel
                self.reg_ids = None
            else:
                dr.eval(regular, params, footprint, near)
                self.reg_ids = dr.compress(regular)
                # parameters and footprints of the regular records, for the kernels
                self.params = {k: dr.gather(mi.Float, v, self.reg_ids) for k, v in params.items()}
                self.footprint = {k: dr.gather(type(v), v, self.reg_ids)
                                  for k, v in footprint.items()}
                self.packed = _pack_records(det, self.params, self.footprint)
            if det.cone:
                self.near_ids = dr.compress(near)
            else:
                self.near_ids = U()
        if identity:
            self.reg_gi, self.reg_vi = None, vi
            self.near_gi, self.near_vi = self.near_ids, dr.gather(U, vi, self.near_ids)
        else:
            self.reg_gi = dr.gather(U, gi, self.reg_ids)
            self.reg_vi = dr.gather(U, vi, self.reg_ids)
            self.near_gi = dr.gather(U, gi, self.near_ids)
            self.near_vi = dr.gather(U, vi, self.near_ids)
        dr.eval(self.reg_vi, self.near_gi, self.near_vi, self.params, self.footprint, self.packed)
        if self.reg_gi is not None:
            dr.eval(self.reg_gi)
        self.n_reg = ngc if identity else dr.width(self.reg_ids)
        self.n_near = dr.width(self.near_ids)
        self._batches = None

    def row_batches(self):
        """(record, row) lane batches of the regular records; kept after the first pass
        when they form a single batch (then the derivative pass reuses them)."""
        if self._batches is not None:
            return self._batches
        if not self.n_reg:
            self._batches = []
            return self._batches
        n_rows = self.footprint["n_rows"]
        total = int(dr.sum(n_rows, axis=None)[0])
        _tick("rows", {"rows_regular": total})
        if total <= ROWS_PER_BATCH:
            # one batch (the training case), expanded on the device: no host round trip
            self._batches = []
            if total:
                rec, offset = segment_lanes(n_rows, 0, total)
                row = mi.Int32(offset) + dr.gather(mi.Int32, self.footprint["row_lo"], rec)
                dr.eval(rec, row)
                self._batches.append((rec, row))
            return self._batches
        return _expand_rows(n_rows.numpy(), self.footprint["row_lo"], ROWS_PER_BATCH)


# ====================================================================== the operation
class _ProjectionSetup:
    """Static configuration of one projection (a plain object: not a PyTree)."""

    def __init__(self, geometry, views, det, n, nviews):
        self.geometry, self.views, self.det, self.n, self.nviews = geometry, views, det, n, nviews


def _vbase(vi, det, v0=0, view=None):
    """Flat index of pixel (0, 0) of each record's view in an image that starts at view v0;
    an opaque scalar where all records are in one ``view`` (no per-lane gather)."""
    if view is not None:
        return dr.opaque(mi.Int32, (view - v0) * det.npix_py)
    return (vi - v0) * det.npix if v0 else vi * det.npix


class _ProjectOp(dr.CustomOp):
    """Differentiable projection; inputs are the Gaussians' arrays (see project_dr)."""

    def eval(self, positions, scales, rotations, densities, density_scale, means2d, setup):
        self.inputs = (positions, scales, rotations, densities, density_scale, means2d)
        self.setup = setup
        gauss = _gaussian_arrays(Gaussians(positions, scales, rotations, densities), density_scale)
        _tick("setup")
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
            _tick("classify")
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
        plan = list(_plan_chunks(setup.n, setup.nviews, setup.det.npix_py))
        for v0, v1, g0, g1 in plan:
            prep = _Prepared(gauss, setup.views, setup.det, v0, v1, g0, g1, means2d, setup.n)
            if len(plan) == 1:
                self._single = prep
            yield prep

    def _record_params(self, gauss, means2d, prep, which):
        setup = self.setup
        det = setup.det
        gi, vi = (prep.reg_gi, prep.reg_vi) if which == "reg" else (prep.near_gi, prep.near_vi)
        frame = _RecordFrame(gauss, setup.views, det, gi, vi, means2d, setup.n)
        return _regular_params(frame, det) if which == "reg" else _near_params(frame)

    def _run(self, prep, gauss, means2d, mode, image, gimage=None, tangent_src=None):
        """Runs one chunk. Returns per-record gradients (backward) as dicts."""
        det = self.setup.det
        out = {}
        if prep.n_reg:
            arrays = (prep.params, prep.footprint, prep.packed)
            tan = None
            if mode == dr.ADMode.Forward:
                tan = tangent_src(prep, "reg")
            v0 = 0 if mode == dr.ADMode.Backward else prep.v0
            one_view = prep.reg_gi is None          # the records are one view's Gaussians
            vbase = _vbase(prep.reg_vi, det, v0, view=prep.v0 if one_view else None)
            if mode == dr.ADMode.Backward:
                sums = _RecordSums(prep.params, prep.n_reg)
            _tick("records", {"records_regular": prep.n_reg})
            for rec, row in prep.row_batches():
                if _PROFILE is not None:
                    _tick("expand")
                    with dr.suspend_grad():
                        *_, lo, hi = _lane_values(det, *arrays, rec, row)
                        cnt = dr.sum(mi.Float(dr.maximum(hi - lo + 1, 0)), axis=None)
                        _tick("count", {"pixels_regular": int(cnt[0])})
                r = _regular_kernel(mode, det, arrays, vbase, rec, row, image, gimage, tan)
                if mode == dr.ADMode.Backward:
                    sums.add(r, rec)
                else:
                    dr.eval(image)
                _tick("kernel_" + mode.name.lower())
            if mode == dr.ADMode.Backward:
                out["reg"] = sums.result()
        if prep.n_near:
            with dr.suspend_grad():
                params = self._record_params(gauss, means2d, prep, "near")
                dr.eval(params)
            tan = tangent_src(prep, "near") if mode == dr.ADMode.Forward else None
            vbase = _vbase(prep.near_vi, det, 0 if mode == dr.ADMode.Backward else prep.v0)
            n_rows = np.full(prep.n_near, det.nv_py, np.uint32)
            row_lo = dr.zeros(mi.Int32, prep.n_near)
            if mode == dr.ADMode.Backward:
                sums = _RecordSums(params, prep.n_near)
            _tick("records", {"records_near": prep.n_near})
            for rec, row in _expand_rows(n_rows, row_lo, ROWS_PER_BATCH):
                r = _near_kernel(mode, det, params, vbase, rec, row, image, gimage, tan)
                if mode == dr.ADMode.Backward:
                    sums.add(r, rec)
                else:
                    dr.eval(image)
                _tick("kernel_near_" + mode.name.lower())
            if mode == dr.ADMode.Backward:
                out["near"] = sums.result()
        return out

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
        pos, sc, rot, den, dsc, md = leaves
        with dr.suspend_grad():
            gauss0 = _gaussian_arrays(Gaussians(*self.inputs[:4]), self.inputs[4])
        _tick("setup_backward")
        for prep in self._chunks(gauss0, self.inputs[5]):
            _tick("classify_backward")
            grads = self._run(prep, gauss0, self.inputs[5], dr.ADMode.Backward, None, gimage)
            if not grads:
                continue
            with dr.resume_grad():
                gauss = _gaussian_arrays(Gaussians(pos, sc, rot, den), dsc)
                for which, acc in grads.items():
                    params = self._record_params(gauss, md, prep, which)
                    live = [k for k, v in params.items() if dr.grad_enabled(v)]
                    for k in live:
                        dr.set_grad(params[k], acc[k])
                    dr.enqueue(dr.ADMode.Backward, *[params[k] for k in live])
                dr.traverse(dr.ADMode.Backward)
            _tick("ad_backward")
        names = ("positions", "scales", "rotations", "densities", "density_scale", "means2d")
        for name, leaf in zip(names, leaves):
            if leaf is not None:
                self.set_grad_in(name, dr.grad(leaf))

    def forward(self):
        names = ("positions", "scales", "rotations", "densities", "density_scale", "means2d")
        leaves = self._leaves()
        for name, leaf in zip(names, leaves):
            if leaf is not None:
                dr.set_grad(leaf, self.grad_in(name))
        pos, sc, rot, den, dsc, md = leaves
        with dr.suspend_grad():
            gauss0 = _gaussian_arrays(Gaussians(*self.inputs[:4]), self.inputs[4])

        def tangent_src(prep, which):
            with dr.resume_grad():
                gauss = _gaussian_arrays(Gaussians(pos, sc, rot, den), dsc)
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
    _validate(gaussians, n, density_scale, means2d, nviews)
    fr = view_frames(geometry)
    setup = _ProjectionSetup(geometry, _ViewFrameArrays(fr),
                             _DetectorConstants(fr, geometry, extent), n, nviews)
    g = gaussians
    flat = dr.custom(_ProjectOp, g.positions, g.scales, g.rotations, g.densities,
                     density_scale, means2d, setup)
    return mi.TensorXf(flat, shape=(nviews, nv, nu))


def project(gaussians: Gaussians, geometry: Geometry, angles=None, extent: float = DEFAULT_EXTENT,
            density_scale=None) -> np.ndarray:
    """Projections [view, v, u] as float32 NumPy line integrals (geometry's length unit)."""
    with dr.suspend_grad():
        img = project_dr(gaussians, geometry, angles, extent, density_scale)
    return np.asarray(img.numpy(), np.float32).reshape(img.shape)
