"""The projector's pixel kernels: one SIMD lane per (record, detector row).

A regular lane loops over its row's footprint pixels, a near-source lane over the whole
row. Each kernel has three modes: ``Primal`` adds the values into the image, ``Forward``
adds the tangent given the record parameters' tangents, ``Backward`` returns per lane the
gradient of <image, gimage> with respect to the record's parameters (summed per record by
``RecordSums``, no per-pixel atomics).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_grg.core import lanes
from mi_grg.core.lanes import expand_fits, pack_rows
from mi_grg.core.projector_records import (BOUND_PAD, NEAR_PARAMS, REGULAR_PARAMS_CONE,
                                           REGULAR_PARAMS_PARALLEL, SQRT_2PI)


def scatter_mode():
    """Per-pixel scatter-adds: per-thread copies on LLVM, atomics elsewhere."""
    return dr.ReduceMode.Expand if dr.backend_v(mi.Float) == dr.JitBackend.LLVM else dr.ReduceMode.Auto


FOOTPRINT_KEYS = ("cu", "cv", "slope", "hw2", "S_vv")   # a footprint row's pixel interval
RECORD_WIDTH = 16          # floats per packed record (parameters + footprint, padded)


def param_keys(det):
    return REGULAR_PARAMS_CONE if det.cone else REGULAR_PARAMS_PARALLEL


def record_keys(det):
    return param_keys(det) + FOOTPRINT_KEYS


def pack_records(det, params, footprint):
    """The records' parameters and footprint values as one [record, 16] array
    (``pack_rows``); None off the LLVM backend."""
    if not lanes.use_packets():
        return None
    return pack_rows([params[k] for k in param_keys(det)]
                     + [footprint[k] for k in FOOTPRINT_KEYS], RECORD_WIDTH)


def row_bounds(det, uc, dv, t):
    """Pixel columns [lo, hi] (Int32, clamped) of a footprint row; dv = row centre - vc,
    ``t`` holds the record's footprint values (``FOOTPRINT_KEYS``)."""
    I32 = mi.Int32
    y = dv - t["cv"]
    hw = (dr.sqrt(dr.maximum(t["hw2"] * (t["S_vv"] - y * y), 0)) * (1 + BOUND_PAD)
          + BOUND_PAD)
    ucr = uc + t["cu"] + t["slope"] * y
    lo = I32(dr.maximum(dr.ceil(dr.clip(ucr - hw - 0.5, -1.0, det.nuf)), 0.0))
    hi = I32(dr.minimum(dr.floor(dr.clip(ucr + hw - 0.5, -1.0, det.nuf)), det.nuf - 1))
    return lo, hi


def row_interval(det, uc, dv, footprint, rec):
    """``row_bounds`` of lanes ``rec`` (gathers the footprint values)."""
    return row_bounds(det, uc, dv, {k: dr.gather(mi.Float, footprint[k], rec)
                                     for k in FOOTPRINT_KEYS})


def lane_values(det, params, footprint, packed, rec, row):
    """Per (record, row) lane: the record's values (dict), the row centre v, dv = v - vc and
    the row's pixel interval [lo, hi]. One packet load per lane where ``packed`` exists."""
    keys = record_keys(det)
    if packed is not None:
        pk = dr.gather(mi.ArrayXf, packed, rec, shape=(RECORD_WIDTH, dr.width(rec)))
        t = {k: pk[i] for i, k in enumerate(keys)}
    else:
        src = {**params, **footprint}
        t = {k: dr.gather(mi.Float, src[k], rec) for k in keys}
    v = mi.Float(row) + 0.5
    dv = v - t["vc"]
    lo, hi = row_bounds(det, t["uc"], dv, t)
    return t, v, dv, lo, hi


def lane_base(vbase, rec):
    """Flat index of pixel (0, 0) of each lane's view: ``vbase`` is an opaque Int32 when
    every record is in the same view, else a per-record UInt32 array."""
    return vbase if isinstance(vbase, mi.Int32) and dr.width(vbase) == 1 \
        else mi.Int32(dr.gather(mi.UInt32, vbase, rec))


class _RegularLane:
    """Row constants of regular (record, row) lanes and the closed form at one pixel."""

    def __init__(self, det, prep_arrays, vbase, rec, row, valid=None):
        params, footprint, packed = prep_arrays
        if valid is not None:    # capacity lanes past the last row: row 0, no pixel
            row = dr.select(valid, row, 0)
        t, v, dv, lo, hi = lane_values(det, params, footprint, packed, rec, row)
        if valid is not None:
            lo, hi = dr.select(valid, lo, 0), dr.select(valid, hi, -1)
        self.t, self.v, self.dv, self.lo, self.hi = t, v, dv, lo, hi
        self.uc, self.N11, self.N21, self.N22, self.amp = (t["uc"], t["N11"], t["N21"],
                                                           t["N22"], t["amp"])
        self.pix0 = lane_base(vbase, rec) + row * det.stride
        self.c1 = self.N21 * dv
        self.y2 = self.N22 * dv
        self.y2sq = self.y2 * self.y2
        self.cone = det.cone
        if det.cone:
            self.D11, self.D21, self.D22 = t["D11"], t["D21"], t["D22"]
            self.pv = dv - t["sv"]
            self.c2 = self.D21 * self.pv - self.D11 * t["su"]
            self.z2 = self.D22 * self.pv
            self.z2p1 = 1 + self.z2 * self.z2
            sv_len = det.a_v + v * det.dv
            self.h2sv2 = det.h2 + sv_len * sv_len
            self.au = det.a_u_row(v)

    def pixel(self, det, u):
        """(du, y1, num, z1, den, 1 / den, m^2, L / sqrt(den) exp(-m^2 / 2)) at column u
        (continuous); z1, den and 1 / den are None for parallel beams."""
        du = u - self.uc
        y1 = dr.fma(self.N11, du, self.c1)
        num = dr.fma(y1, y1, self.y2sq)
        if self.cone:
            z1 = dr.fma(self.D11, du, self.c2)
            den = dr.fma(z1, z1, self.z2p1)
            su_len = dr.fma(u, det.du, self.au)
            # L / sqrt(den) = sqrt(L^2 / den): one reciprocal and one square root per pixel
            inv_den = dr.rcp(den)
            m2 = num * inv_den
            L_rs = dr.sqrt(dr.fma(su_len, su_len, self.h2sv2) * inv_den)
            base0 = L_rs * dr.exp(-0.5 * dr.minimum(m2, det.E2))
            return du, y1, num, z1, den, inv_den, m2, base0
        m2 = num
        base0 = dr.exp(-0.5 * dr.minimum(m2, det.E2))
        return du, y1, num, None, None, None, m2, base0


def regular_kernel(mode, det, prep_arrays, vbase, rec, row, image, gimage=None, tan=None,
                   valid=None):
    """One lane per (record, detector row); loops over the row's footprint pixels.

    ``prep_arrays`` = (params, footprint, packed) of the records. Mode
    ``dr.ADMode.Primal``: add the values into ``image`` (rows ``det.stride`` apart; on LLVM
    ``lanes.PACKET`` pixels per store); ``Backward``: return the gradient of <image, gimage>
    w.r.t. the 11 (6 parallel) record parameters per lane; ``Forward``: scatter-add the
    tangent given the parameter tangents ``tan``. ``valid`` (mi.Bool, optional) marks
    the lanes that hold a row; the others add nothing."""
    lane = _RegularLane(det, prep_arrays, vbase, rec, row, valid)
    if mode == dr.ADMode.Forward:
        return _regular_forward(det, lane, rec, image, tan)
    if mode == dr.ADMode.Primal and lanes.use_packets():
        return _regular_primal_packets(det, lane, image)
    if mode == dr.ADMode.Primal:
        return _regular_primal(det, lane, image)
    return _regular_backward(det, lane, gimage)


def _regular_primal_packets(det, lane, image):
    """Primal pass in PACKET-aligned blocks of the row; pixels outside [lo, hi] (or the
    footprint) add 0. pix0 is a multiple of PACKET (det.stride is), so block =
    pix0 / PACKET + b."""
    F = mi.Float
    W = lanes.PACKET
    blk0 = mi.UInt32(lane.pix0) // W
    lo, hi, amp = lane.lo, lane.hi, lane.amp

    def body(b):
        j0 = b * W
        u0 = F(j0) + 0.5
        vals = []
        for k in range(W):
            m2, base0 = lane.pixel(det, u0 + k)[-2:]
            act = (m2 <= det.E2) & (j0 + k >= lo) & (j0 + k <= hi)
            vals.append(dr.select(act, amp * base0, 0.0))
        dr.scatter_add(image, mi.ArrayXf(vals), blk0 + mi.UInt32(b), mode=dr.ReduceMode.Expand)
        return (b + 1,)
    dr.while_loop((lo // W,), lambda b: b <= hi // W, body, labels=("b",), label="rg_primal_packet")


def _regular_primal(det, lane, image):
    """Primal pass, one scatter-add per pixel."""
    smode = scatter_mode()

    def body(j):
        m2, base0 = lane.pixel(det, mi.Float(j) + 0.5)[-2:]
        dr.scatter_add(image, lane.amp * base0, mi.UInt32(lane.pix0 + j), active=m2 <= det.E2,
                       mode=smode)
        return (j + 1,)
    dr.while_loop((lane.lo,), lambda j: j <= lane.hi, body, labels=("j",), label="rg_primal")


def _regular_forward(det, lane, rec, image, tan):
    """Tangent image: d value from the record parameters' tangents ``tan``."""
    tt = {k: dr.gather(mi.Float, tan[k], rec) for k in param_keys(det)}
    smode = scatter_mode()
    t, dv, y2 = lane.t, lane.dv, lane.y2

    def body(j):
        du, y1, num, z1, den, inv_den, m2, base0 = lane.pixel(det, mi.Float(j) + 0.5)
        val = lane.amp * base0
        # d num and d den from the parameter tangents
        dnum = 2 * y1 * (tt["N11"] * du + tt["N21"] * dv - lane.N11 * tt["uc"] - lane.N21 * tt["vc"]) \
            + 2 * y2 * (tt["N22"] * dv - lane.N22 * tt["vc"])
        dval = base0 * tt["amp"]
        if det.cone:
            pu = du - t["su"]
            pv, z2 = lane.pv, lane.z2
            dden = 2 * z1 * (tt["D11"] * pu + tt["D21"] * pv - lane.D11 * (tt["uc"] + tt["su"])
                             - lane.D21 * (tt["vc"] + tt["sv"])) \
                + 2 * z2 * (tt["D22"] * pv - lane.D22 * (tt["vc"] + tt["sv"]))
            dval = dval + val * 0.5 * inv_den * ((m2 - 1) * dden - dnum)
        else:
            dval = dval - 0.5 * val * dnum
        dr.scatter_add(image, dval, mi.UInt32(lane.pix0 + j), active=m2 <= det.E2, mode=smode)
        return (j + 1,)
    dr.while_loop((lane.lo,), lambda j: j <= lane.hi, body, labels=("j",), label="rg_forward")


def _regular_backward(det, lane, gimage):
    """Per-lane gradient of <image, gimage> w.r.t. the record parameters, from seven
    per-lane sums over the row's pixels."""
    F = mi.Float
    cone = det.cone
    zero = F(0)

    def body(j, Sa, Sy1du, Sy1, SN, Sz1pu, Sz1, SD):
        du, y1, num, z1, den, inv_den, m2, base0 = lane.pixel(det, F(j) + 0.5)
        act = m2 <= det.E2
        g = dr.gather(F, gimage, mi.UInt32(lane.pix0 + j), active=act)
        gb = g * base0
        gI = gb * lane.amp
        Sa = Sa + gb
        if cone:
            tq = 0.5 * gI * inv_den
            gN = -tq
            gD = tq * (m2 - 1)
            pu = du - lane.t["su"]
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

    state = (lane.lo, zero, zero, zero, zero, zero, zero, zero)
    _, Sa, Sy1du, Sy1, SN, Sz1pu, Sz1, SD = dr.while_loop(
        state, lambda j, *a: j <= lane.hi, body,
        labels=("j", "Sa", "Sy1du", "Sy1", "SN", "Sz1pu", "Sz1", "SD"), label="rg_backward")
    dv, y2, N11, N21, N22 = lane.dv, lane.y2, lane.N11, lane.N21, lane.N22
    gr = dict(amp=Sa, N11=2 * Sy1du, N21=2 * dv * Sy1, N22=2 * y2 * dv * SN,
              uc=-2 * N11 * Sy1, vc=-2 * (N21 * Sy1 + N22 * y2 * SN))
    if cone:
        pv, z2 = lane.pv, lane.z2
        gr.update(D11=2 * Sz1pu, D21=2 * pv * Sz1, D22=2 * z2 * pv * SD,
                  su=-2 * lane.D11 * Sz1, sv=-2 * (lane.D21 * Sz1 + lane.D22 * z2 * SD))
        gr["uc"] = gr["uc"] + gr["su"]
        gr["vc"] = gr["vc"] + gr["sv"]
    return gr


class RecordSums:
    """Per-record sums of the backward's per-lane gradients, over one or more row batches.

    On LLVM (when the per-thread copies stay below ``lanes.EXPAND_BYTES``) a lane adds its
    sums with one contiguous packet store into a [record, width] array; otherwise one
    scatter-add per parameter (reduced within a SIMD packet first)."""

    def __init__(self, keys, n):
        self.keys, self.n = tuple(keys), n
        self.width = 1 << max(len(self.keys) - 1, 0).bit_length()
        self.packed = lanes.use_packets() and expand_fits(n * self.width)
        if self.packed:
            self.acc = dr.zeros(mi.Float, n * self.width)
        else:
            self.acc = {k: dr.zeros(mi.Float, n) for k in self.keys}

    def add(self, sums, rec, evaluate: bool = True):
        """Add one batch's per-lane sums into their records (``evaluate=False``: left
        lazy, e.g. inside a symbolic conditional; the caller evaluates ``acc``)."""
        if self.packed:
            vals = [sums[k] for k in self.keys]
            vals += [dr.zeros(mi.Float, dr.width(rec))] * (self.width - len(vals))
            dr.scatter_add(self.acc, mi.ArrayXf(vals), rec, mode=dr.ReduceMode.Expand)
        else:
            for k in self.keys:
                dr.scatter_add(self.acc[k], sums[k], rec, mode=dr.ReduceMode.Local)
        if evaluate:
            dr.eval(self.acc)

    def result(self) -> dict:
        if not self.packed:
            return self.acc
        pk = dr.gather(mi.ArrayXf, self.acc, dr.arange(mi.UInt32, self.n),
                       shape=(self.width, self.n))
        out = {k: mi.Float(pk[i]) for i, k in enumerate(self.keys)}
        dr.eval(out)
        return out


def phi(x):
    """Standard normal CDF (float32; erf form, exact enough for a multiplicative factor)."""
    return 0.5 * (1.0 + dr.erf(x * (1.0 / math.sqrt(2.0))))


class _NearLane:
    """Row constants of near-source (record, row) lanes and the exact half-line form
    rho sqrt(2 pi / a) exp(-m^2/2) Phi(s) at one pixel."""

    def __init__(self, det, params, vbase, rec, row, valid=None):
        F = mi.Float
        # the row's last pixel; -1 (no pixel) for a recorded step's empty slots
        self.last = det.nu - 1 if valid is None else dr.select(valid, det.nu - 1, -1)
        gather = lambda a: dr.gather(F, a, rec)  # noqa: E731
        t = {k: gather(params[k]) for k in NEAR_PARAMS}
        self.M = [[t[f"M{l}{k}"] for k in range(3)] for l in range(3)]
        self.gv = [t["g0"], t["g1"], t["g2"]]
        self.amp = t["amp"]
        v = F(row) + 0.5
        self.sv_len = det.a_v + v * det.dv
        self.h2sv2 = det.h2 + self.sv_len * self.sv_len
        self.au = det.a_u_row(v)
        M = self.M
        self.kl = [M[l][0] * det.h + M[l][2] * self.sv_len for l in range(3)]   # row-constant part of M r
        self.pix0 = lane_base(vbase, rec) + row * det.stride

    def pixel(self, det, j):
        """(su_len, D = M r, q = |D|^2, c = D x g, 1 / |D|, m^2, s, L / |D| exp(-m^2/2),
        Phi(s)) at pixel column j."""
        M, gv = self.M, self.gv
        u = mi.Float(j) + 0.5
        su_len = dr.fma(u, det.du, self.au)
        L = dr.sqrt(dr.fma(su_len, su_len, self.h2sv2))
        D = [dr.fma(M[l][1], su_len, self.kl[l]) for l in range(3)]
        q = dr.maximum(D[0] * D[0] + D[1] * D[1] + D[2] * D[2], 1e-30)
        c = [D[1] * gv[2] - D[2] * gv[1], D[2] * gv[0] - D[0] * gv[2], D[0] * gv[1] - D[1] * gv[0]]
        pp = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        tdot = D[0] * gv[0] + D[1] * gv[1] + D[2] * gv[2]
        rq = dr.rsqrt(q)
        m2 = pp * rq * rq
        s = tdot * rq
        base0 = L * rq * dr.exp(-0.5 * dr.minimum(m2, det.E2))
        Phi = phi(s)
        return su_len, D, q, c, rq, m2, s, base0, Phi

    def partials(self, D, q, c, rq, m2, s, base0, Phi):
        """Partials of I w.r.t. D (3), g (3) and amp, as (gD, gg, base0 * Phi)."""
        amp, gv = self.amp, self.gv
        val = amp * base0 * Phi
        phi_s = dr.exp(-0.5 * dr.minimum(s * s, 174.0)) * (1.0 / SQRT_2PI)
        iq = rq * rq
        Iq = 0.5 * iq * (val * (m2 - 1) - amp * base0 * phi_s * s)
        Ip = -0.5 * val * iq
        It = amp * base0 * phi_s * rq
        xc = [gv[1] * c[2] - gv[2] * c[1], gv[2] * c[0] - gv[0] * c[2], gv[0] * c[1] - gv[1] * c[0]]
        cd = [c[1] * D[2] - c[2] * D[1], c[2] * D[0] - c[0] * D[2], c[0] * D[1] - c[1] * D[0]]
        gD = [2 * D[l] * Iq + 2 * Ip * xc[l] + It * gv[l] for l in range(3)]
        gg = [2 * Ip * cd[l] + It * D[l] for l in range(3)]
        return gD, gg, base0 * Phi


def near_kernel(mode, det, params, vbase, rec, row, image, gimage=None, tan=None,
                valid=None):
    """One lane per (near record, detector row) over the whole row; exact half-line form.
    Modes as in ``regular_kernel`` (13 record parameters, ``NEAR_PARAMS``); lanes not
    ``valid`` (mi.Bool, optional) add nothing."""
    lane = _NearLane(det, params, vbase, rec, row, valid)
    if mode == dr.ADMode.Primal:
        return _near_primal(det, lane, image)
    if mode == dr.ADMode.Forward:
        return _near_forward(det, lane, rec, image, tan)
    return _near_backward(det, lane, gimage)


def _near_primal(det, lane, image):
    j0, last = mi.Int32(0), lane.last
    smode = scatter_mode()

    def body(j):
        _, _, _, _, _, m2, _, base0, Phi = lane.pixel(det, j)
        dr.scatter_add(image, lane.amp * base0 * Phi, mi.UInt32(lane.pix0 + j), active=m2 <= det.E2,
                       mode=smode)
        return (j + 1,)
    dr.while_loop((j0,), lambda j: j <= last, body, labels=("j",), label="rg_near_primal")


def _near_forward(det, lane, rec, image, tan):
    tt = {k: dr.gather(mi.Float, tan[k], rec) for k in NEAR_PARAMS}
    j0, last = mi.Int32(0), lane.last
    smode = scatter_mode()

    def body(j):
        su_len, D, q, c, rq, m2, s, base0, Phi = lane.pixel(det, j)
        gD, gg, bphi = lane.partials(D, q, c, rq, m2, s, base0, Phi)
        dval = bphi * tt["amp"]
        for l in range(3):
            dD = tt[f"M{l}0"] * det.h + tt[f"M{l}1"] * su_len + tt[f"M{l}2"] * lane.sv_len
            dval = dval + gD[l] * dD + gg[l] * tt[f"g{l}"]
        dr.scatter_add(image, dval, mi.UInt32(lane.pix0 + j), active=m2 <= det.E2, mode=smode)
        return (j + 1,)
    dr.while_loop((j0,), lambda j: j <= last, body, labels=("j",), label="rg_near_forward")


def _near_backward(det, lane, gimage):
    F = mi.Float
    j0, last = mi.Int32(0), lane.last
    zero = F(0)

    def body(j, *acc):
        su_len, D, q, c, rq, m2, s, base0, Phi = lane.pixel(det, j)
        act = m2 <= det.E2
        g = dr.gather(F, gimage, mi.UInt32(lane.pix0 + j), active=act)
        gD, gg, bphi = lane.partials(D, q, c, rq, m2, s, base0, Phi)
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
        gr[f"M{l}2"] = acc[l] * lane.sv_len
        gr[f"g{l}"] = acc[6 + l]
    return gr
