"""Density voxelizer for radiative Gaussians, in Dr.Jit (differentiable, chunked).

    sigma(x) = sum_i rho_i exp(-1/2 m_i(x)^2) [m_i(x) <= extent],
    m_i(x)^2 = (x - p_i)^T Sigma_i^-1 (x - p_i),

sampled at the voxel CENTRES of a ``Geometry`` (``geometry.voxel_axes()``): voxel (i, j, k)
is centred at ``-sVoxel/2 + (index + 0.5) * dVoxel + offOrigin``. Volumes are [x, y, z];
densities are in 1/length (the unit of the Gaussians' densities).

Method (work proportional to the number of (Gaussian, voxel) pairs, not N x voxels):

1. Per Gaussian its voxel box: the axis-aligned bounding box of the ellipsoid
   m <= extent, whose half-widths are exactly ``extent * sqrt(diag(Sigma))``, clipped to
   the requested block of voxels.
2. Pair expansion, at the level of (Gaussian, x, y) *columns* of the box: the boxes'
   column counts are laid end to end; an exclusive ``dr.prefix_sum`` gives each
   Gaussian's first column, a marker scatter and an inclusive prefix sum give every
   column lane its Gaussian, the remainder its (x, y) within the box.
3. Each column lane solves m^2(z) = extent^2 for its exact z-range inside the ellipsoid
   (~half of the box's voxels) and loops over those voxels (a symbolic loop, no
   per-voxel gathers): rho exp(-m^2/2), ``dr.scatter_add`` into the voxel. Voxels are
   contiguous along z ([x, y, z] order), so a lane writes consecutive addresses; on the
   LLVM backend, when the block's z size is a multiple of ``PACKET``, it writes them
   ``PACKET`` voxels per packet store, and lanes read their Gaussian's values with one
   packet load from a packed array of the chunk (``_pack_chunk``).
   The backward pass expands (Gaussian, x) *slices* instead, one lane looping over the
   slice's columns and their voxels, so that the per-lane gradient sums need one atomic
   per slice rather than per column.

Columns (slices) are processed in chunks of at most ``chunk_pairs`` (Gaussian, voxel)
pairs (cut anywhere, also inside one Gaussian's box), so memory stays bounded by the volume
plus one chunk of lanes, for 256^3 volumes and 10^6 Gaussians alike.

Truncation: ``DEFAULT_EXTENT`` is the projector's (``mi_grg.core.projector``) so that both use
one number; the projector cuts a Gaussian where the *ray's* Mahalanobis distance exceeds
it, the voxelizer where the *point's* does. Both differ from the untruncated field by at
most rho exp(-extent^2/2) (4e-5 rho at 4.5).

Derivatives (``voxelize_dr``) flow to positions, scales, rotations, densities and
``density_scale`` through a ``dr.CustomOp`` whose forward/backward passes recompute the
pairs chunk by chunk with the analytic derivatives of rho exp(-m^2/2) with respect to
rho, p and Sigma^-1; Sigma^-1 comes from ``mi_grg.core.gaussians.inverse_covariance`` under
Dr.Jit's normal AD. The backward pass accumulates each slice's gradient in registers
(one atomic per slice and parameter, not per voxel). The truncation boundary is treated
as fixed (its jump is rho exp(-extent^2/2)).

Inputs are checked as the projector checks them (finite, scales > 0, densities >= 0,
rotations unit quaternions to ``gaussians.QUATERNION_TOL``, zero ones rejected), and the
rotations are normalised internally, so the rotation gradient is tangent to the unit sphere.

Where it lives: ``voxelizer_plan`` (the pair plan: boxes, columns, chunks, capacities);
this module holds the kernels and the differentiable operation.
"""
from __future__ import annotations

import math

import numpy as np

import drjit as dr
import mitsuba as mi

# one set of input checks, one quaternion normalisation, one lane layout and one
# truncation rule for the projector and the voxelizer
from mi_grg.core.gaussians import (Gaussians, first_failure, gaussian_checks, inverse_covariance,
                                   unit_quaternions)
from mi_grg.core.geometry import Geometry
from mi_grg.core.lanes import PACKET, expand_fits, pack_rows, segment_lanes, use_packets
from mi_grg.core.projector import DEFAULT_EXTENT
from mi_grg.core.voxelizer_plan import (_FLOAT_DIV_MAX, _Plan, _block_start,  # noqa: F401
                                        _plan, capacity_plan)


#: Default (Gaussian, voxel) pairs per chunk; a column counts as its voxels + 8, so a chunk
#: holds <= 2^24 / 9 columns (two UInt32 temporaries each: ~15 MB).
DEFAULT_CHUNK_PAIRS = 1 << 24

#: exp() argument floor: float32 exp underflows to denormals below about -87.
_EXP_FLOOR = -87.0


class VoxelizerError(ValueError):
    """Invalid voxelizer input; the message names the argument."""


# ---------------------------------------------------------------- validation
def _check_block(block, geometry: Geometry):
    n = tuple(int(x) for x in geometry.nVoxel)
    if block is None:
        return (0, 0, 0), n
    try:
        start, size = block
        start = tuple(int(x) for x in np.asarray(start).reshape(-1))
        size = tuple(int(x) for x in np.asarray(size).reshape(-1))
    except (TypeError, ValueError):
        raise VoxelizerError(f"block must be (start [x, y, z], size [x, y, z]) voxel counts, "
                             f"got {block!r}") from None
    if len(start) != 3 or len(size) != 3:
        raise VoxelizerError(f"block must be (start [3], size [3]), got {block!r}")
    for k in range(3):
        if size[k] < 1 or start[k] < 0 or start[k] + size[k] > n[k]:
            raise VoxelizerError(
                f"block (start={start}, size={size}) must lie inside nVoxel={n} with size >= 1")
    return start, size


def _check_inputs(gaussians, extent, density_scale):
    if not isinstance(gaussians, Gaussians):
        raise VoxelizerError(f"gaussians must be mi_grg.core.gaussians.Gaussians, "
                             f"got {type(gaussians).__name__}")
    extent = float(extent)
    if not (math.isfinite(extent) and extent > 0):
        raise VoxelizerError(f"extent (Mahalanobis truncation radius) must be finite and > 0, "
                             f"got {extent!r}")
    n = len(gaussians)
    g = gaussians
    for name, arr in (("positions", g.positions), ("scales", g.scales),
                      ("rotations", g.rotations)):
        for c in arr:
            if dr.width(c) != n:
                raise VoxelizerError(f"{name} must have N={n} rows (shape [N, {len(arr)}]), "
                                     f"got {dr.width(c)}")
    if density_scale is not None:
        if not isinstance(density_scale, mi.Float):
            arr = np.asarray(density_scale, np.float32).reshape(-1)
            density_scale = mi.Float(arr)
        if dr.width(density_scale) != n:
            raise VoxelizerError(f"density_scale must have shape [N] = [{n}] (one factor per "
                                 f"Gaussian), got width {dr.width(density_scale)}")
    if n:
        # the projector's checks (finite, scales > 0, densities >= 0, unit quaternions),
        # all in one reduction: voxelize_dr runs on every training iteration
        msg = first_failure(g, gaussian_checks(g, density_scale))
        if msg is not None:
            raise VoxelizerError(msg)
    return extent, density_scale


_LANE_WIDTH = 16   # floats per packed Gaussian (see _pack_chunk)


def _pack_chunk(plan: _Plan, ids, p, a, rho):
    """The values a lane reads of each Gaussian of a chunk (row = position in ``ids``):
    p (3), Sigma^-1 (6), rho, the box's first x and y voxel and its y size, as one
    row-major [len(ids), 16] array that a lane reads with one packet load (LLVM; see
    ``lanes.use_packets``); None elsewhere (lanes gather each value)."""
    if not use_packets():
        return None
    Float = mi.Float
    vals = [dr.gather(Float, c, ids) for c in list(p) + list(a) + [rho]]
    # box indices are < 2^24 voxels: exact in float32
    vals += [Float(dr.gather(type(x), x, ids)) for x in (plan.lo[0], plan.lo[1], plan.n[1])]
    return pack_rows(vals, _LANE_WIDTH)


def _gaussian_values(plan: _Plan, g, slot, p, a, rho, packed) -> dict:
    """Gaussian g's values (one lane each), from the packed chunk (row ``slot``) or by
    gathers."""
    Int32, UInt32, Float = mi.Int32, mi.UInt32, mi.Float
    if packed is not None:
        pk = dr.gather(mi.ArrayXf, packed, slot, shape=(_LANE_WIDTH, dr.width(slot)))
        return {"p": (pk[0], pk[1], pk[2]), "a": tuple(pk[3 + k] for k in range(6)),
                "rho": pk[9], "lo0": Int32(pk[10]), "lo1": Int32(pk[11]), "ny": UInt32(pk[12])}
    return {"p": tuple(dr.gather(Float, c, g) for c in p),
            "a": tuple(dr.gather(Float, c, g) for c in a), "rho": dr.gather(Float, rho, g),
            "lo0": dr.gather(Int32, plan.lo[0], g), "lo1": dr.gather(Int32, plan.lo[1], g),
            "ny": dr.gather(UInt32, plan.n[1], g)}


def _lane(plan: _Plan, g, ix, v: dict) -> dict:
    """Gaussian g's values ``v`` and its box's x slice ix (one lane each)."""
    Int32, Float = mi.Int32, mi.Float
    ax = v["lo0"] + Int32(ix)
    px, py, pz = v["p"]
    return {"g": g, "ax": ax, "ay0": v["lo1"], "ny": v["ny"],
            "dx": dr.opaque(Float, plan.x0[0]) + (Float(ax) + 0.5) * dr.opaque(Float, plan.d[0]) - px,
            "py": py, "pz": pz, "a": v["a"], "rho": v["rho"]}


def _slices(plan: _Plan, ids, skip: int, n_slices: int, p, a, rho, packed=None,
            segments=None) -> dict:
    """The (Gaussian, x) slices of one chunk, one lane each. Left unevaluated: it fuses
    into the loop kernel. ``segments``: (counts, slot, ix) of ``_segments`` if made."""
    counts, slot, ix = segments or _segments(plan.nslice, ids, skip, n_slices)
    g = dr.gather(mi.UInt32, ids, slot)
    lane = _lane(plan, g, ix, _gaussian_values(plan, g, slot, p, a, rho, packed))
    if plan.masked:      # a lane past the last slice loops over no column
        lane["ny"] = dr.select(ix < dr.gather(mi.UInt32, counts, slot), lane["ny"], 0)
    return lane


def _segments(units, ids, skip: int, n: int):
    """(counts, slot, offset): the ``units`` (columns or slices per Gaussian) of the
    Gaussians ``ids`` expanded into ``n`` lanes (``segment_lanes``: evaluated kernels)."""
    counts = dr.gather(mi.UInt32, units, ids)
    slot, offset = segment_lanes(counts, skip, n)
    return counts, slot, offset


def _columns(plan: _Plan, ids, skip: int, n_cols: int, p, a, rho, packed=None,
             segments=None):
    """The (Gaussian, x, y) columns of one chunk, one lane each: (lane, column).
    ``segments``: (counts, slot, local) of ``_segments`` if made."""
    UInt32, Float = mi.UInt32, mi.Float
    counts, slot, local = segments or _segments(plan.ncol, ids, skip, n_cols)
    g = dr.gather(UInt32, ids, slot)
    v = _gaussian_values(plan, g, slot, p, a, rho, packed)
    # >= 1 also in the idle lanes of the last SIMD packet (their gathers give 0)
    ny = dr.maximum(v["ny"], 1)
    if plan.max_columns < _FLOAT_DIV_MAX:
        # local // ny in float32: SIMD integer division does not exist on x86 (LLVM emits
        # one scalar division per lane). Exact: local < nx ny < 2^22 and (local + 1/2) / ny
        # stays >= 1 / (2 ny) away from an integer, far above float32 rounding.
        ix = UInt32(dr.floor((Float(local) + 0.5) / Float(ny)))
    else:
        ix = local // ny
    lane = _lane(plan, g, ix, v)
    col = _column(plan, lane, local - ix * ny)
    if plan.masked:      # a lane past the last column has no voxel
        col["count"] = dr.select(local < dr.gather(UInt32, counts, slot), col["count"], 0)
    return lane, col


def _column(plan: _Plan, lane: dict, iy) -> dict:
    """Column iy of a slice: its exact z-range inside the ellipsoid m <= extent (the roots
    of the quadratic m^2(z) = extent^2, clipped to the block)."""
    UInt32, Int32, Float = mi.UInt32, mi.Int32, mi.Float
    x0 = [dr.opaque(Float, v) for v in plan.x0]
    dv = [dr.opaque(Float, v) for v in plan.d]
    a00, a01, a02, a11, a12, a22 = lane["a"]
    dx = lane["dx"]
    ay = lane["ay0"] + Int32(iy)
    dy = x0[1] + (Float(ay) + 0.5) * dv[1] - lane["py"]
    # m^2(dz) = a22 dz^2 + 2 beta dz + gamma along the column
    beta = a02 * dx + a12 * dy
    gamma = dx * (a00 * dx + 2 * a01 * dy) + a11 * dy * dy
    disc = dr.square(beta) - a22 * (gamma - dr.opaque(Float, plan.ext2))
    inv_a22 = dr.rcp(a22)
    half = dr.sqrt(dr.maximum(disc, 0)) * inv_a22 * (1 + 1e-4)   # widened: m^2 test decides
    zc = lane["pz"] - beta * inv_a22
    inv_dz = dr.rcp(dv[2])
    zs = _block_start(plan.start, 2, Float)
    ze = _block_start(plan.start, 2, Float, plan.size[2])
    z_first = dr.clip(dr.ceil((zc - half - x0[2]) * inv_dz - 0.5), zs, ze)
    z_last = dr.clip(dr.floor((zc + half - x0[2]) * inv_dz - 0.5), zs - 1, ze - 1)
    count = UInt32(dr.select(disc >= 0, dr.maximum(z_last - z_first + 1, 0), 0))
    az = Int32(z_first)
    st = [_block_start(plan.start, k, Int32) for k in range(3)]
    sy = dr.opaque(Int32, plan.size[1])
    sz = dr.opaque(Int32, plan.size[2])
    return {"count": count, "z0": az - st[2],
            "base": UInt32(((lane["ax"] - st[0]) * sy + (ay - st[1])) * sz + (az - st[2])),
            "dy": dy, "dz0": x0[2] + (Float(az) + 0.5) * dv[2] - lane["pz"],
            "beta2": 2 * beta, "gamma": gamma}


def _column_m2(c: dict, a22, dz):
    """m^2 at offset dz along column c: a22 dz^2 + 2 beta dz + gamma."""
    return c["gamma"] + dz * (c["beta2"] + a22 * dz)


def _falloff(m2):
    """exp(-m^2 / 2), floored before float32 exp underflows."""
    return dr.exp(dr.maximum(-0.5 * m2, _EXP_FLOOR))


def _voxel_loop(plan: _Plan, lane: dict, c: dict, state: tuple, step):
    """Run ``step(c, k, dz, m2, inside, *state) -> state`` over the voxels k of column c
    (a symbolic loop, no per-voxel gathers)."""
    Float = mi.Float
    dzv = dr.opaque(Float, plan.d[2])
    ext2 = dr.opaque(Float, plan.ext2)
    a22 = lane["a"][5]
    count, dz0 = c["count"], c["dz0"]

    def body(k, *st):
        dz = dr.fma(Float(k), dzv, dz0)
        m2 = _column_m2(c, a22, dz)
        return (k + 1, *step(c, k, dz, m2, m2 <= ext2, *st))

    out = dr.while_loop((dr.zeros(mi.UInt32, dr.width(lane["g"])), *state),
                        lambda k, *st: k < count, body, label="voxelize_column")
    return out[1:]


def _column_loop(plan: _Plan, lane: dict, state: tuple, step):
    """``_voxel_loop`` over every column of each slice lane (an outer symbolic loop)."""
    def column_body(iy, *st):
        return (iy + 1, *_voxel_loop(plan, lane, _column(plan, lane, iy), st, step))

    out = dr.while_loop((dr.zeros(mi.UInt32, dr.width(lane["g"])), *state),
                        lambda iy, *st: iy < lane["ny"], column_body, label="voxelize_slice")
    return out[1:]


def _use_packets(plan: _Plan) -> bool:
    """Packet stores along z (LLVM; see ``lanes.use_packets``): the block's z size must be
    a whole number of packets (then every column starts on a packet boundary) and its
    per-thread copies must stay small."""
    return use_packets() and plan.size[2] % PACKET == 0 and expand_fits(int(np.prod(plan.size)))


def _packet_column(plan: _Plan, lane: dict, c: dict, out, r):
    """Add column c's densities into ``out`` PACKET voxels per store: the packet-aligned
    blocks of the column's z-range, voxels outside the range (or the ellipsoid) add 0."""
    Float, Int32, UInt32 = mi.Float, mi.Int32, mi.UInt32
    W = PACKET
    dzv = dr.opaque(Float, plan.d[2])
    ext2 = dr.opaque(Float, plan.ext2)
    a22 = lane["a"][5]
    z0, count = c["z0"], Int32(c["count"])
    z1 = z0 + count - 1
    blk0 = (c["base"] - UInt32(z0)) // W         # the column's first packet
    dz_col = c["dz0"] - Float(z0) * dzv           # dz of the block's voxel z = 0

    def body(b):
        zb = b * W
        vals = []
        for k in range(W):
            dz = dr.fma(Float(zb + k), dzv, dz_col)
            m2 = _column_m2(c, a22, dz)
            inside = (m2 <= ext2) & (zb + k >= z0) & (zb + k <= z1)
            vals.append(dr.select(inside, r * _falloff(m2), 0.0))
        dr.scatter_add(out, mi.ArrayXf(vals), blk0 + UInt32(b), mode=dr.ReduceMode.Expand)
        return (b + 1,)

    # count > 0: an empty column (its z-range clipped away) runs no block
    dr.while_loop((z0 // W,), lambda b: (b <= z1 // W) & (count > 0), body,
                  label="voxelize_column_packet")


def _capacity_lanes(plan: _Plan, n: int, total, fn) -> None:
    """Run ``fn()`` (a chunk's lanes: set-up, loops, scatters; no return value) on the
    first ``total`` (mi.UInt32 [1]) of ``n`` lanes of a capacity plan, inside a symbolic
    conditional: the lanes past the total form the tail, so whole SIMD packets (LLVM) skip
    them rather than run their set-up masked. Elsewhere ``fn()`` runs on every lane."""
    if not plan.masked:
        fn()
        return
    valid = dr.arange(mi.UInt32, n) < total
    dr.if_stmt((), valid, lambda: (fn(), ())[1], lambda: (), mode="symbolic",
               label="voxelize_capacity")


def _chunk_inputs(plan: _Plan, units, ids, skip: int, n: int, p, a, rho):
    """(packed values, segments) of one chunk. A capacity plan makes both before the
    conditional of ``_capacity_lanes`` (nothing may be evaluated inside it; the segments'
    prefix sums run here), and packs once: its column and slice chunks share their ids,
    so the backward pass reuses the forward's values. Elsewhere the segments are left to
    the lanes (None; made there, as before)."""
    if not plan.masked:
        return _pack_chunk(plan, ids, p, a, rho), None
    if plan.packed is None:
        plan.packed = _pack_chunk(plan, ids, p, a, rho)
        dr.eval(plan.packed)
    return plan.packed, _segments(units, ids, skip, n)


def _forward(plan: _Plan, p, a, rho):
    Float = mi.Float
    out = dr.zeros(Float, int(np.prod(plan.size)))
    packets = _use_packets(plan)
    for ids, skip, n_cols in plan.col_chunks:
        packed, segments = _chunk_inputs(plan, plan.ncol, ids, skip, n_cols, p, a, rho)

        def lanes():
            lane, col = _columns(plan, ids, skip, n_cols, p, a, rho, packed, segments)
            r = lane["rho"]
            if packets:
                _packet_column(plan, lane, col, out, r)
                return

            def step(c, k, dz, m2, inside):
                val = r * _falloff(m2)
                # Direct: lanes hit distinct addresses, a packet-local reduction only costs
                dr.scatter_add(out, val, c["base"] + k, active=inside,
                               mode=dr.ReduceMode.Direct)
                return ()

            _voxel_loop(plan, lane, col, (), step)

        _capacity_lanes(plan, n_cols, plan.totals and plan.totals[0], lanes)
        dr.eval(out)   # one chunk at a time: bounded memory
    return out


def _terms(lane, c, dz, m2, inside):
    """Per voxel: A d, exp(-m^2/2) (0 outside the ellipsoid)."""
    a00, a01, a02, a11, a12, a22 = lane["a"]
    dx, dy = lane["dx"], c["dy"]
    ad = (a00 * dx + a01 * dy + a02 * dz, a01 * dx + a11 * dy + a12 * dz,
          a02 * dx + a12 * dy + a22 * dz)
    e = dr.select(inside, _falloff(m2), 0.0)
    return ad, e


class _VoxelizeOp(dr.CustomOp):
    """rho, p, Sigma^-1 entries -> flat block volume; derivatives by per-chunk recompute."""

    def eval(self, p, a, rho, plan):
        self.p, self.a, self.rho, self.plan = p, a, rho, plan
        return _forward(plan, p, a, rho)

    def forward(self):
        Float = mi.Float
        n = dr.width(self.rho)
        tp = [dr.zeros(Float, n) + t for t in self.grad_in("p")]
        ta = [dr.zeros(Float, n) + t for t in self.grad_in("a")]
        trho = dr.zeros(Float, n) + self.grad_in("rho")
        out = dr.zeros(Float, int(np.prod(self.plan.size)))
        for ids, skip, n_cols in self.plan.col_chunks:
            lane, col = _columns(self.plan, ids, skip, n_cols, self.p, self.a, self.rho)
            g, dx, r = lane["g"], lane["dx"], lane["rho"]
            t = [dr.gather(Float, x, g) for x in tp]
            s = [dr.gather(Float, x, g) for x in ta]
            tr = dr.gather(Float, trho, g)

            def step(c, k, dz, m2, inside):
                dy, base = c["dy"], c["base"]
                ad, e = _terms(lane, c, dz, m2, inside)
                val = r * e
                quad = (s[0] * dx * dx + s[3] * dy * dy + s[5] * dz * dz
                        + 2 * (s[1] * dx * dy + s[2] * dx * dz + s[4] * dy * dz))
                dval = e * tr + val * (ad[0] * t[0] + ad[1] * t[1] + ad[2] * t[2] - 0.5 * quad)
                dr.scatter_add(out, dval, base + k, active=inside, mode=dr.ReduceMode.Direct)
                return ()

            _voxel_loop(self.plan, lane, col, (), step)
            dr.eval(out)
        self.set_grad_out(out)

    def backward(self):
        Float = mi.Float
        go = self.grad_out()
        n = dr.width(self.rho)
        gp = [dr.zeros(Float, n) for _ in range(3)]
        ga = [dr.zeros(Float, n) for _ in range(6)]
        grho = dr.zeros(Float, n)
        mode = dr.ReduceMode.Local   # neighbouring slices mostly share their Gaussian
        plan = self.plan
        for ids, skip, n_slices in plan.slice_chunks:
            packed, segments = _chunk_inputs(plan, plan.nslice, ids, skip, n_slices, self.p,
                                             self.a, self.rho)

            def lanes():
                lane = _slices(plan, ids, skip, n_slices, self.p, self.a, self.rho, packed,
                               segments)
                g, dx, r = lane["g"], lane["dx"], lane["rho"]

                def step(c, k, dz, m2, inside, sp, sa, sr):
                    dy = c["dy"]
                    ad, e = _terms(lane, c, dz, m2, inside)
                    gv = dr.gather(Float, go, c["base"] + k, inside)
                    w = gv * r * e
                    # d val/d p = val A d; d val/d A_ij = -1/2 val d_i d_j (x2 off the
                    # diagonal)
                    sp = tuple(acc + w * x for acc, x in zip(sp, ad))
                    sa = tuple(acc + w * x for acc, x in zip(sa, (
                        -0.5 * dx * dx, -dx * dy, -dx * dz, -0.5 * dy * dy, -dy * dz,
                        -0.5 * dz * dz)))
                    return sp, sa, sr + gv * e

                zero = dr.zeros(Float, dr.width(g))
                sp, sa, sr = _column_loop(plan, lane, ((zero,) * 3, (zero,) * 6, zero), step)
                # one atomic per slice and parameter (sums over the slice's voxels)
                for acc, x in zip(gp + ga + [grho], list(sp) + list(sa) + [sr]):
                    dr.scatter_add(acc, x, g, mode=mode)

            _capacity_lanes(plan, n_slices, plan.totals and plan.totals[1], lanes)
            dr.eval(gp, ga, grho)
        self.set_grad_in("p", mi.Point3f(*gp))
        self.set_grad_in("a", ga)
        self.set_grad_in("rho", grho)

    def name(self):
        return "voxelize"


def _plan_and_precision(g: Gaussians, geometry, start, size, extent, chunk_pairs):
    """The pair plan and the six entries (a00, a01, a02, a11, a12, a22) of Sigma^-1, both
    from the normalised rotations (as the projector: gradient tangent to the sphere)."""
    q = unit_quaternions(g.rotations)
    plan = _plan(g.positions, g.scales, q, geometry, start, size, extent, chunk_pairs)
    A = inverse_covariance(g.scales, q)
    return plan, [A[0][0], A[0][1], A[0][2], A[1][1], A[1][2], A[2][2]]


# ---------------------------------------------------------------- public API
def voxelize_dr(gaussians: Gaussians, geometry: Geometry, block=None, extent=None,
                density_scale=None, chunk_pairs: int = DEFAULT_CHUNK_PAIRS):
    """Density at the voxel centres, as a differentiable Dr.Jit tensor [x, y, z].

    Args:
        gaussians: the Gaussians (positions/scales in the geometry's length unit,
            densities in 1/length).
        geometry: supplies the voxel grid (nVoxel, sVoxel, offOrigin).
        block: ``(start [x, y, z], size [x, y, z])`` voxel indices: only this sub-block
            is filled (e.g. a random 32^3 block for 3-D regularisation); None: the
            whole grid.
        extent: truncation radius in Mahalanobis units (default ``DEFAULT_EXTENT``).
        density_scale: optional mi.Float [N] multiplying each Gaussian's density (the
            graph-augmented field of GR-Gaussian); differentiable.
        chunk_pairs: (Gaussian, voxel) pairs per chunk (bounds temporary memory).
    Returns:
        mi.TensorXf of shape ``size`` (nVoxel without ``block``), float32 densities.
        Differentiable with respect to positions, scales, rotations, densities and
        density_scale.
    """
    if not isinstance(geometry, Geometry):
        raise VoxelizerError(f"geometry must be a mi_grg.Geometry, got {type(geometry).__name__}")
    start, size = _check_block(block, geometry)
    extent = DEFAULT_EXTENT if extent is None else extent
    extent, density_scale = _check_inputs(gaussians, extent, density_scale)
    chunk_pairs = int(chunk_pairs)
    if chunk_pairs < 1:
        raise VoxelizerError(f"chunk_pairs must be >= 1, got {chunk_pairs}")
    if int(np.prod(size)) >= 2 ** 31:
        raise VoxelizerError(f"block size {size} has >= 2^31 voxels (32-bit indices)")
    n_out = int(np.prod(size))
    if len(gaussians) == 0:
        return mi.TensorXf(dr.zeros(mi.Float, n_out), size)
    g = gaussians
    rho = g.densities if density_scale is None else g.densities * density_scale
    plan, a = _plan_and_precision(g, geometry, start, size, extent, chunk_pairs)
    p = mi.Point3f(g.positions)
    if dr.grad_enabled(p, a, rho):
        flat = dr.custom(_VoxelizeOp, p, a, rho, plan)
    else:
        flat = _forward(plan, p, a, rho)
    return mi.TensorXf(flat, size)


def voxelize_block_capacity(gaussians: Gaussians, geometry: Geometry, start, size, extent,
                            density_scale, caps):
    """``voxelize_dr`` of one block inside a recorded training step: the block's corner on
    the device (3 x mi.Int32 [1]), the pairs as capacities (``capacity_plan``, ``caps``
    with ``cols`` and ``slices``), and no input checks (host reads)."""
    g = gaussians
    rho = g.densities if density_scale is None else g.densities * density_scale
    q = unit_quaternions(g.rotations)
    size = tuple(int(x) for x in size)
    plan = capacity_plan(g.positions, g.scales, q, geometry, start, size, float(extent), caps)
    A = inverse_covariance(g.scales, q)
    a = [A[0][0], A[0][1], A[0][2], A[1][1], A[1][2], A[2][2]]
    flat = dr.custom(_VoxelizeOp, mi.Point3f(g.positions), a, rho, plan)
    return mi.TensorXf(flat, size)


def voxelize(gaussians: Gaussians, geometry: Geometry, block=None, extent=None,
             density_scale=None, chunk_pairs: int = DEFAULT_CHUNK_PAIRS) -> np.ndarray:
    """``voxelize_dr`` without derivatives, as a float32 NumPy array [x, y, z]."""
    with dr.suspend_grad():
        vol = voxelize_dr(gaussians, geometry, block=block, extent=extent,
                          density_scale=density_scale, chunk_pairs=chunk_pairs)
        return np.asarray(vol.numpy(), np.float32)


def pair_count(gaussians: Gaussians, geometry: Geometry, block=None, extent=None) -> dict:
    """Work counts for benchmarks: ``box_pairs`` (sum of the clipped voxel boxes) and
    ``pairs`` (voxels inside the ellipsoids' z-ranges, the pairs actually evaluated)."""
    start, size = _check_block(block, geometry)
    extent = DEFAULT_EXTENT if extent is None else float(extent)
    g = gaussians
    if len(g) == 0:
        return {"box_pairs": 0, "pairs": 0}
    with dr.suspend_grad():
        plan, a = _plan_and_precision(g, geometry, start, size, extent, DEFAULT_CHUNK_PAIRS)
        pairs = sum(int(dr.sum(_columns(plan, *chunk, g.positions, a, g.densities)[1]["count"],
                                   axis=None)[0]) for chunk in plan.col_chunks)
    return {"box_pairs": plan.box_pairs, "pairs": int(pairs)}
