"""The closed form per (Gaussian, view) record: its frame, parameters and footprint.

A record is one Gaussian seen from one view, expressed in that view's frame (e_n towards
the detector, e_u, e_v) relative to the source and in pixel offsets from the Gaussian's
projected centre; lengths are divided by the Gaussian's largest scale so that every
record is O(1) in float32 (the cancellation-safe forms are derived in
``mi_grg.core.projector``). Regular records get 11 (parallel beam: 6) parameters and an
exact footprint ellipse; near-source records get the whitening matrix of the half-line form.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core import lanes
from mi_grg.core.gaussians import Gaussians, rotation_matrix, unit_quaternions
from mi_grg.core.geometry import Geometry
from mi_grg.core.lanes import to_dr
from mi_grg.core.view_frames import ViewFrames

HALF_LINE_MARGIN = 8.0        # Mahalanobis units between source and closest point (regular)
BOUND_PAD = 1e-3              # relative/absolute slack of the footprint (pixels)
_J_MIN = 0.05                 # smallest eigenvalue of the footprint's perspective factor J
SQRT_2PI = math.sqrt(2.0 * math.pi)


class DetectorConstants:
    """Geometry scalars as opaque Dr.Jit values (one compiled kernel for all geometries);
    the detector values are those of view ``view`` of ``fr`` (all views of one launch
    share them, ``ViewFrames.groups``). ``skewed`` (a Python flag, ``ViewFrames.skewed``):
    the records and kernels carry the pixel lattice's shear ``sk``; a rectangular grid's
    kernels are those without it."""

    def __init__(self, fr: ViewFrames, geometry: Geometry, extent: float, view: int = 0):
        F = mi.Float
        nv, nu = geometry.nDetector
        self.cone = fr.cone
        self.nu_py, self.nv_py = nu, nv
        # Internal images store rows ``stride`` floats apart: nu rounded up to a whole
        # number of packets where the primal pass writes packets (cropped on the way out)
        stride = -(-nu // lanes.PACKET) * lanes.PACKET if lanes.use_packets() else nu
        self.stride_py = stride
        self.stride = dr.opaque(mi.Int32, stride)
        h, a_u, a_v, du, dv, sk = fr.detector_values(view)
        self.h = dr.opaque(F, h)
        self.h2 = dr.opaque(F, h * h)
        self.a_u, self.a_v = dr.opaque(F, a_u), dr.opaque(F, a_v)
        self.du, self.dv = dr.opaque(F, du), dr.opaque(F, dv)
        self.skewed = fr.skewed
        self.sk = dr.opaque(F, sk) if fr.skewed else None
        self.E = dr.opaque(F, extent)
        self.E2 = dr.opaque(F, extent * extent)
        self.Eb2 = dr.opaque(F, (extent * (1 + BOUND_PAD)) ** 2)
        self.margin2 = dr.opaque(F, extent * extent + HALF_LINE_MARGIN ** 2)
        self.nu, self.nv = dr.opaque(mi.Int32, nu), dr.opaque(mi.Int32, nv)
        self.nuf, self.nvf = dr.opaque(F, float(nu)), dr.opaque(F, float(nv))
        self.npix = dr.opaque(mi.UInt32, stride * nv)
        self.npix_py = stride * nv      # floats per view of an internal image

    def override(self, det) -> None:
        """Take a per-view scan's detector values from ``det``, a float32 array holding
        (h, h^2, a_u, a_v, du, dv, sk) (``step.view_arrays``): width-1 gathers, so that a
        recorded step reads them as inputs."""
        vals = [dr.gather(mi.Float, det, mi.UInt32(k)) for k in range(7 if self.skewed else 6)]
        self.h, self.h2, self.a_u, self.a_v, self.du, self.dv = vals[:6]
        if self.skewed:
            self.sk = vals[6]

    def a_u_row(self, v):
        """The detector-plane e_u coordinate of column 0 on row ``v`` (continuous): a_u,
        plus the shear's v sk on a skewed detector."""
        return dr.fma(v, self.sk, self.a_u) if self.skewed else self.a_u

    def to_pixels(self, x, y):
        """Pixel offsets (u, v) of the detector-plane offsets (x, y) along (e_u, e_v)."""
        v = y / self.dv
        if self.skewed:
            x = x - v * self.sk
        return x / self.du, v


class ViewFrameArrays:
    """Per-view frame vectors as Dr.Jit arrays (float32), indexed by global view id."""

    def __init__(self, fr: ViewFrames):
        self.e = [[to_dr(mi.Float, axis[:, k]) for k in range(3)] for axis in (fr.e_n, fr.e_u, fr.e_v)]
        # origin coordinates in the view frame, in float64 before rounding
        self.o = [to_dr(mi.Float, np.sum(fr.origin * axis, 1)) for axis in (fr.e_n, fr.e_u, fr.e_v)]

    @classmethod
    def of(cls, e, o) -> "ViewFrameArrays":
        """Frame arrays given as Dr.Jit arrays (e: 3 x 3, o: 3), e.g. a recording's inputs."""
        fa = cls.__new__(cls)
        fa.e, fa.o = e, o
        return fa


def gaussian_arrays(g: Gaussians, density_scale):
    """Per-Gaussian Dr.Jit quantities shared by all views (differentiable).

    Rotations are normalised here (as ``Gaussians.from_raw`` does), so that Sigma^-1 =
    R S^-2 R^T = Sigma^-1 of ``gaussians.inverse_covariance`` holds exactly and the rotation
    gradient is tangent to the unit sphere."""
    R = rotation_matrix(unit_quaternions(g.rotations))
    rho = g.densities if density_scale is None else g.densities * density_scale
    return {"p": [g.positions.x, g.positions.y, g.positions.z],
            "s": [g.scales.x, g.scales.y, g.scales.z],
            "R": [[R[i][j] for j in range(3)] for i in range(3)], "rho": rho}


class RecordFrame:
    """Quantities of a set of records (Gaussian index gi, view index vi) in the view frame,
    lengths divided by sigma = max scale (detached) so that every record is O(1)."""

    def __init__(self, gauss, views: ViewFrameArrays, det: DetectorConstants, gi, vi,
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
            shift_u = md.x * det.du if det.sk is None else dr.fma(md.x, det.du, md.y * det.sk)
            X[1] = X[1] + shift_u * depth
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


def sigma_entry(frame, i, j):
    """Sigma'_{ij} (normalised) = sum_l s_l^2 Rf_il Rf_jl."""
    return sum(dr.square(frame.sn[l]) * frame.Rf[i][l] * frame.Rf[j][l] for l in range(3))


def ghat2(frame):
    """|g|^2 = X^T Sigma^-1 X (Mahalanobis distance source-centre, squared)."""
    acc = 0
    for l in range(3):
        gl = frame.Rf[0][l] * frame.Xn[0] + frame.Rf[1][l] * frame.Xn[1] + frame.Rf[2][l] * frame.Xn[2]
        acc = acc + dr.square(gl / frame.sn[l])
    return acc


def regular_params(frame: RecordFrame, det: DetectorConstants):
    """The 11 per-record parameters of the regular closed form (differentiable).

    Pixel (u, v) (continuous), du = u - uc, dv = v - vc:
        y1 = N11 du + N21 dv, y2 = N22 dv,  num = y1^2 + y2^2
        pu = du - su, pv = dv - sv, z1 = D11 pu + D21 pv, z2 = D22 pv, den = 1 + z1^2 + z2^2
        m^2 = num / den,  value = amp * L(u, v) / sqrt(den) * exp(-m^2 / 2)
    with L the source-pixel distance (cone; parallel: den = L = 1)."""
    sn, Rf, Xn = frame.sn, frame.Rf, frame.Xn
    S_nn, S_nu, S_nv = sigma_entry(frame, 0, 0), sigma_entry(frame, 0, 1), sigma_entry(frame, 0, 2)
    det_s = dr.square(sn[0] * sn[1] * sn[2])
    dun, dvn = det.du * frame.isig, det.dv * frame.isig     # pixel steps / sigma
    if det.cone:
        xn, xu, xv = Xn
        lam = det.h / frame.X[0]
        uc, vc = det.to_pixels(lam * frame.X[1] - det.a_u, lam * frame.X[2] - det.a_v)
        # numerator: (Dq x X)^T Sigma (Dq x X) = Delta^T Wn Delta, t_l = s_l R_l^T w
        tu = [sn[l] * (Rf[0][l] * xv - Rf[2][l] * xn) for l in range(3)]
        tv = [sn[l] * (Rf[1][l] * xn - Rf[0][l] * xu) for l in range(3)]
        tuu = sum(t * t for t in tu)
        w_uu = dr.square(dun) * tuu
        w_uv = dun * dvn * sum(tu[l] * tv[l] for l in range(3))
        if det.skewed:   # the lattice's shear: W_pix = J^T W J, J = [[du, sk], [0, dv]]
            w_uv = dr.fma(dun * det.sk * frame.isig, tuu, w_uv)
        n11r = dr.sqrt(w_uu)
        ghat = dr.sqrt(ghat2(frame))
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
        A_uv_pix = dvn * A_uv
        if det.skewed:
            A_uv_pix = dr.fma(det.sk * frame.isig, A_uu, A_uv_pix)
        D21 = A_uv_pix * ra / beta
        D22 = dvn * dr.sqrt(S_nn / det_s) * ra / beta   # det(A_uv block) = Sigma_nn / det Sigma
        su, sv = det.to_pixels(-lam * (frame.X[1] - frame.X[0] * S_nu / S_nn),
                               -lam * (frame.X[2] - frame.X[0] * S_nv / S_nn))
        amp = frame.rho * (SQRT_2PI * frame.sig) * dr.sqrt(S_nn) / det.h
        return dict(uc=uc, vc=vc, N11=N11, N21=N21, N22=N22, D11=D11, D21=D21, D22=D22,
                    su=su, sv=sv, amp=amp)
    # parallel: m^2 = Delta_phys^T Sigma_uv^-1 Delta_phys, value = rho sqrt(2 pi / A_nn) e^(-m^2/2)
    S_uu, S_uv, S_vv = sigma_entry(frame, 1, 1), sigma_entry(frame, 1, 2), sigma_entry(frame, 2, 2)
    A_nn = sum(dr.square(Rf[0][l] / sn[l]) for l in range(3))
    det_uv = det_s * A_nn                            # det of Sigma's (u, v) block
    r_vv = dr.rsqrt(S_vv)
    rd = dr.rsqrt(det_uv)
    N21 = -dvn * S_uv * r_vv * rd
    if det.skewed:    # Q_pix = J^T Q J as in the cone's numerator
        N21 = dr.fma(det.sk * frame.isig * dr.sqrt(S_vv), rd, N21)
    uc, vc = det.to_pixels(frame.X[1], frame.X[2])
    return dict(uc=uc, vc=vc, N11=dun * dr.sqrt(S_vv) * rd, N21=N21, N22=dvn * r_vv,
                amp=frame.rho * (SQRT_2PI * frame.sig) * dr.rsqrt(A_nn))


REGULAR_PARAMS_CONE = ("uc", "vc", "N11", "N21", "N22", "D11", "D21", "D22", "su", "sv", "amp")
REGULAR_PARAMS_PARALLEL = ("uc", "vc", "N11", "N21", "N22", "amp")
NEAR_PARAMS = ("M00", "M01", "M02", "M10", "M11", "M12", "M20", "M21", "M22", "g0", "g1", "g2", "amp")


def near_params(frame: RecordFrame):
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
    out.update(g0=g[0], g1=g[1], g2=g[2], amp=frame.rho * (SQRT_2PI * frame.sig))
    return out


def footprint_ellipse(params, det: DetectorConstants):
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
    rv = dr.sqrt(dr.maximum(S_vv, 0)) * (1 + BOUND_PAD) + BOUND_PAD
    ru = dr.sqrt(dr.maximum(S_uu, 0)) * (1 + BOUND_PAD) + BOUND_PAD
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


