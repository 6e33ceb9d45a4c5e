"""How the projector's and the voxelizer's kernels lay out their SIMD lanes.

Packets (LLVM backend only): a lane writes ``PACKET`` consecutive pixels (voxels) with one
contiguous store and reads its record with one packet load, because a per-element
``scatter_add`` resolves conflicts between SIMD lanes one lane at a time on the CPU.
CUDA keeps per-element atomics, which it executes natively. Segment expansion: items of
variable-length segments (a record's detector rows, a Gaussian's voxel columns) become
one lane each.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["EXPAND_BYTES", "PACKET", "expand_fits", "pack_rows", "segment_lanes", "to_dr",
           "use_packets"]

PACKET = 4                  # pixels (voxels) per packet store on LLVM (see use_packets)
EXPAND_BYTES = 1 << 29      # largest per-thread copy of a packet-store target


def use_packets() -> bool:
    """Whether the kernels use packet loads and stores (the LLVM backend).

    On the CPU a per-pixel ``scatter_add`` resolves conflicts between the SIMD lanes one
    lane at a time; it dominated the projector's primal pass, and the backward's eleven
    per-record scatter-adds a large share of its kernel. With packets, a lane evaluates its
    row ``PACKET`` pixels at a time and adds them with one contiguous store, the backward
    adds a lane's sums to its record with one contiguous store, and each lane reads its
    record with one packet load (docs/benchmarks.md, "Training step"). CUDA keeps the
    per-pixel atomics, which it executes natively."""
    return dr.backend_v(mi.Float) == dr.JitBackend.LLVM


def expand_fits(n_floats: int) -> bool:
    """Whether ReduceMode.Expand's per-thread copies of an ``n_floats`` target stay within
    ``EXPAND_BYTES`` (the packet stores' condition, with ``use_packets()``)."""
    return n_floats * 4 * dr.thread_count() <= EXPAND_BYTES


def pack_rows(vals: list, width: int):
    """Per-row values (``len(vals) <= width`` arrays of one width n) as one row-major
    [n, width] array (lazy), which a lane reads with one packet load
    (``dr.gather(mi.ArrayXf, packed, row, shape=(width, lanes))``)."""
    n = dr.width(vals[0])
    vals = list(vals) + [dr.zeros(mi.Float, n)] * (width - len(vals))
    packed = dr.zeros(mi.Float, n * width)
    dr.scatter(packed, mi.ArrayXf(vals), dr.arange(mi.UInt32, n))
    return packed


def to_dr(T, a):
    """NumPy -> Dr.Jit array, padded to >= 2 entries: width-1 host arrays become scalar kernel
    inputs whose load alignment follows the (varying) address, which defeats the kernel cache."""
    a = np.asarray(a)
    dtype = {mi.Float: np.float32, mi.UInt32: np.uint32, mi.Int32: np.int32}[T]
    if a.size < 2:
        a = np.concatenate([a.reshape(-1), np.zeros(2 - a.size)])
    return T(np.ascontiguousarray(a, dtype))


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
    # per-thread copies of the LLVM backend's default ReduceMode.Expand) it would make a
    # new kernel, compiled anew, on every projection and TV block
    in_range = pos < dr.opaque(UInt32, total)
    dr.scatter_add(marker, UInt32(1), pos, active=(k > 0) & in_range, mode=dr.ReduceMode.Local)
    slot = dr.prefix_reduce(dr.ReduceOp.Add, marker, exclusive=False)
    offset = dr.arange(UInt32, total) + skip_u - dr.gather(UInt32, first, slot)
    return slot, offset
