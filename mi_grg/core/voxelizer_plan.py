"""The voxelizer's pair plan: which (Gaussian, voxel) pairs of a block each Gaussian's
E-ellipsoid covers, as columns (x, y) of z-slices, cut into chunks of bounded size; in a
recorded training step the same plan with capacities instead of host-read counts
(``capacity_plan``). The kernels that evaluate the pairs: ``mi_grg.core.voxelizer``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core.gaussians import rotation_matrix

#: Cost of one column in units of voxel pairs when cutting chunks (its set-up).
_COLUMN_COST = 8


@dataclass
class _Plan:
    """Which (Gaussian, voxel) pairs exist and how they are cut into chunks."""
    start: tuple          # block start [x, y, z] (voxel indices)
    size: tuple           # block size [x, y, z]
    lo: list              # 3 x mi.Int32 [N]: first voxel index of each box (absolute)
    n: list               # 3 x mi.UInt32 [N]: box size in voxels per axis (clipped)
    ncol: object          # mi.UInt32 [N]: (x, y) columns per box (0: misses the block)
    nslice: object        # mi.UInt32 [N]: x slices per box (0: misses the block)
    col_chunks: list      # [(ids mi.UInt32, skip int, columns int)]
    slice_chunks: list    # [(ids mi.UInt32, skip int, slices int)]
    x0: tuple             # grid corner [x, y, z] (length): voxel i centre = x0 + (i+.5) d
    d: tuple              # voxel size [x, y, z] (length)
    ext2: float           # extent^2
    box_pairs: int        # sum of the box volumes (an upper bound of the pairs)
    max_columns: int      # largest column count of one box
    masked: bool = False  # lanes past the last column / slice (a capacity plan): masked
    totals: tuple = None  # a capacity plan's (columns, slices) totals (mi.UInt32 [1])
    packed: object = None  # a capacity plan's packed values, shared by both passes


#: Boxes with fewer columns than this split their column index in float32 (exact there).
_FLOAT_DIV_MAX = 1 << 22


def _cut_chunks(ids, units, weight, chunk_pairs: int) -> list:
    """Cut the sequence of ``units`` (columns or slices) of the Gaussians ``ids``, laid end
    to end, into chunks of <= ``chunk_pairs`` total ``weight`` (one unit's weight per
    Gaussian), anywhere, also inside one Gaussian's box: [(ids, skip, units)]."""
    chunks = []
    if not ids.size:
        return chunks
    cols, w = units[ids], weight[ids]
    c_end = np.cumsum(cols)
    c_start = c_end - cols
    w_end = np.cumsum(cols * w)
    w_start = w_end - cols * w
    total_cols = int(c_end[-1])
    c0 = 0
    while c0 < total_cols:
        g0 = int(np.searchsorted(c_end, c0, side="right"))
        target = w_start[g0] + (c0 - c_start[g0]) * w[g0] + chunk_pairs
        g1 = int(np.searchsorted(w_end, target, side="right"))
        if g1 >= ids.size:
            c1 = total_cols
        else:
            c1 = int(c_start[g1] + (target - w_start[g1]) // w[g1])
        c1 = max(min(c1, total_cols), c0 + 1)
        b = int(np.searchsorted(c_start, c1, side="left"))
        chunks.append((mi.UInt32(ids[g0:b].astype(np.uint32)), int(c0 - c_start[g0]), c1 - c0))
        c0 = c1
    return chunks


def _block_start(start, k: int, T, plus: int = 0):
    """Block corner (+ ``plus``) along axis k as an opaque T: from a Python int (a traced
    plan) or from a device mi.Int32 [1] (a recorded step's: the block is not baked in)."""
    s = start[k]
    if isinstance(s, (int, np.integer)):
        return dr.opaque(T, int(s) + plus)
    return T(s) + plus if plus else T(s)


def _boxes(positions, scales, rotations, geometry, start, size, extent):
    """Each Gaussian's voxel box clipped to the block: first voxel (3 x mi.Int32 [N]) and
    size (3 x mi.UInt32 [N], 0 where it misses), evaluated; the grid corner and voxel size."""
    Float, Int32, UInt32 = mi.Float, mi.Int32, mi.UInt32
    p = dr.detach(positions)
    s = dr.detach(scales)
    R = rotation_matrix(dr.detach(rotations))
    sv = (s.x, s.y, s.z)
    x0 = tuple(-0.5 * sz + o for sz, o in zip(geometry.sVoxel, geometry.offOrigin))
    d = tuple(geometry.dVoxel)
    lo, nn = [], []
    for k in range(3):
        var = dr.square(R[k][0] * sv[0]) + dr.square(R[k][1] * sv[1]) + dr.square(R[k][2] * sv[2])
        # exact half-width of the ellipsoid's box; a relative 1e-5 widening makes the
        # float32 box conservative (the m^2 test decides at the edge)
        h = extent * dr.sqrt(var) * (1 + 1e-5)
        pk = (p.x, p.y, p.z)[k]
        a = dr.opaque(Float, x0[k])
        inv_d = dr.opaque(Float, 1.0 / d[k])
        first = dr.ceil((pk - h - a) * inv_d - 0.5)
        last = dr.floor((pk + h - a) * inv_d - 0.5)
        b0 = _block_start(start, k, Float)
        b1 = _block_start(start, k, Float, size[k])
        first = dr.clip(first, b0, b1)              # clip before any int conversion
        last = dr.clip(last, b0 - 1, b1 - 1)
        lo.append(Int32(first))
        nn.append(UInt32(dr.maximum(last - first + 1, 0)))
    dr.eval(lo, nn)
    return lo, nn, x0, d


def _plan(positions, scales, rotations, geometry, start, size, extent, chunk_pairs) -> _Plan:
    lo, nn, x0, d = _boxes(positions, scales, rotations, geometry, start, size, extent)
    UInt32 = mi.UInt32
    nx, ny, nz = (np.asarray(x, np.int64) for x in nn)
    nslice = nx.copy()
    nslice[(ny == 0) | (nz == 0)] = 0
    ncol = nslice * ny
    ids = np.nonzero(nslice)[0]
    # forward: one lane per (x, y) column; backward: one lane per x slice (its columns in
    # an outer loop), so that its per-lane sums need 1/ny of the atomics
    return _Plan(start=start, size=size, lo=lo, n=nn, ncol=UInt32(ncol.astype(np.uint32)),
                 nslice=UInt32(nslice.astype(np.uint32)),
                 col_chunks=_cut_chunks(ids, ncol, nz + _COLUMN_COST, chunk_pairs),
                 slice_chunks=_cut_chunks(ids, nslice, ny * (nz + _COLUMN_COST), chunk_pairs),
                 x0=x0, d=d, ext2=extent * extent, box_pairs=int(np.sum((ncol * nz)[ids])),
                 max_columns=int(ncol.max()) if ncol.size else 0)


def capacity_plan(positions, scales, rotations, geometry, start, size, extent, caps) -> _Plan:
    """The pair plan of a recorded training step: no host read. ``start``: 3 device
    mi.Int32 [1]; one chunk of ``caps.cols`` column lanes (``caps.slices`` slice lanes
    backward) over every Gaussian, the lanes past the boxes' columns (slices) skipped
    (``_capacity_lanes``); their totals left on the device in ``caps.cols_total`` /
    ``caps.slices_total`` for the caller (past the capacity, pairs are missing). Boxes
    are clipped to the block, so a box's columns never exceed size[0] size[1] (the
    float32 division's bound)."""
    lo, nn, x0, d = _boxes(positions, scales, rotations, geometry, start, size, extent)
    UInt32 = mi.UInt32
    nslice = dr.select((nn[1] == 0) | (nn[2] == 0), 0, nn[0])
    ncol = nslice * nn[1]
    caps.cols_total, caps.slices_total = dr.sum(ncol), dr.sum(nslice)
    dr.eval(nslice, ncol, caps.cols_total, caps.slices_total)
    ids = dr.arange(UInt32, dr.width(ncol))
    return _Plan(start=start, size=size, lo=lo, n=nn, ncol=ncol, nslice=nslice,
                 col_chunks=[(ids, 0, caps.cols)], slice_chunks=[(ids, 0, caps.slices)],
                 x0=x0, d=d, ext2=extent * extent, box_pairs=-1,
                 max_columns=size[0] * size[1], masked=True,
                 totals=(caps.cols_total, caps.slices_total))
