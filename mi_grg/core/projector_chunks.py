"""The projector's work plan: chunks of records, their classification, and row batches.

A chunk is a block of views x Gaussians small enough for the record arrays and the chunk's
own image; its records are classified (regular: footprint ellipse; near-source: whole
detector; behind the source: dropped) and the regular records' rows expanded into lanes.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.core.lanes import segment_lanes, to_dr
from mi_grg.core.projector_kernels import pack_records
from mi_grg.core.projector_records import (RecordFrame, footprint_ellipse, ghat2, regular_params,
                                           sigma_entry)


def plan_chunks(n: int, n_views: int, npix: int, records_per_chunk: int, pixels_per_chunk: int):
    """(v0, v1, g0, g1) blocks of at most ``records_per_chunk`` records and
    ``pixels_per_chunk`` image floats (view-major)."""
    vmax = max(1, pixels_per_chunk // npix)
    if n * n_views <= records_per_chunk and n_views <= vmax:
        yield 0, n_views, 0, n
        return
    vpc = max(1, min(records_per_chunk // n, vmax))
    gpc = min(n, records_per_chunk)
    for v0 in range(0, n_views, vpc):
        for g0 in range(0, n, gpc):
            yield v0, min(n_views, v0 + vpc), g0, min(n, g0 + gpc)


def expand_rows(n_rows_np: np.ndarray, row_lo, max_items: int):
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
            rec = dr.gather(mi.UInt32, to_dr(mi.UInt32, sel), k)
            first = dr.gather(mi.UInt32, to_dr(mi.UInt32, offs), k)
            row = mi.Int32(dr.arange(mi.UInt32, cnt) - first) + dr.gather(mi.Int32, row_lo, rec)
            dr.eval(rec, row)
            yield rec, row
        start = end


class PreparedChunk:
    """Classification and footprints of one chunk (all detached): views [v0, v1) x
    Gaussians [g0, g1), records view-major (index = view * (g1 - g0) + Gaussian)."""

    def __init__(self, gauss, views, det, v0, v1, g0, g1, means2d, n_gauss, caps=None):
        U = mi.UInt32
        self.v0, self.v1 = v0, v1
        # caps (``RowCapacity``, a recorded training step's): no host read, the lanes a
        # fixed capacity, the counts left on the device for the caller to check
        self.caps = caps
        nvc, ngc = v1 - v0, g1 - g0
        # One view and every Gaussian (a training iteration): the records are the Gaussians
        # themselves, indexed directly (gi = None) and not compacted to the regular ones
        # (non-regular records get no rows).
        identity = (nvc == 1 and ngc == n_gauss
                    and (means2d is None or dr.width(means2d) == n_gauss))
        if caps is not None and not identity:
            raise ValueError("a row capacity needs one view and every Gaussian in one chunk")
        gi = None if identity else g0 + dr.tile(dr.arange(U, ngc), nvc)
        vi = v0 + dr.repeat(dr.arange(U, nvc), ngc)
        dr.eval(vi)   # keeps the sizes (literals) out of the big kernels below
        if gi is not None:
            dr.eval(gi)
        with dr.suspend_grad():
            frame = RecordFrame(gauss, views, det, gi, vi, means2d, n_gauss)
            params = regular_params(frame, det)
            footprint = footprint_ellipse(params, det)
            if det.cone:
                S_nn = sigma_entry(frame, 0, 0)
                reach = frame.Xn[0] + det.E * dr.sqrt(S_nn)       # front-most depth of the E-ellipsoid
                regular = footprint["ok"] & (frame.Xn[0] > 0) & (ghat2(frame) >= det.margin2)
                near = ~regular & (reach > 0)
            else:
                regular = footprint["ok"]
                near = None
            regular = regular & (footprint["n_rows"] > 0)
            footprint.pop("ok")
            if identity:
                footprint["n_rows"] = dr.select(regular, footprint["n_rows"], 0)
                self.params, self.footprint = params, footprint
                self.packed = pack_records(det, params, footprint)
                dr.eval(params, footprint, near, self.packed)   # one kernel
                self.reg_ids = None
            else:
                dr.eval(regular, params, footprint, near)
                self.reg_ids = dr.compress(regular)
                # parameters and footprints of the regular records, for the kernels
                self.params = {k: dr.gather(mi.Float, v, self.reg_ids) for k, v in params.items()}
                self.footprint = {k: dr.gather(type(v), v, self.reg_ids)
                                  for k, v in footprint.items()}
                self.packed = pack_records(det, self.params, self.footprint)
            if caps is not None:
                self.near_ids = self._capacity_near(near if det.cone else None, ngc)
            elif det.cone:
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
        self.n_near = dr.width(self.near_ids)   # a recorded step's: its capacity
        self._batches = None

    def row_batches(self, rows_per_batch: int):
        """(record, row) lane batches of at most ``rows_per_batch`` lanes of the regular
        records; kept after the first pass when they form a single batch (then the
        derivative pass reuses them)."""
        if self._batches is not None:
            return self._batches
        if not self.n_reg:
            self._batches = []
            return self._batches
        n_rows = self.footprint["n_rows"]
        if self.caps is not None:
            self._batches = [self._capacity_lanes(n_rows, self.caps.rows)]
            return self._batches
        total = int(dr.sum(n_rows, axis=None)[0])
        if total <= rows_per_batch:
            # one batch (the training case), expanded on the device: no host round trip
            self._batches = []
            if total:
                rec, offset = segment_lanes(n_rows, 0, total)
                row = mi.Int32(offset) + dr.gather(mi.Int32, self.footprint["row_lo"], rec)
                dr.eval(rec, row)
                self._batches.append((rec, row))
            return self._batches
        return expand_rows(n_rows.numpy(), self.footprint["row_lo"], rows_per_batch)

    def _capacity_near(self, near, n: int):
        """The near-source records packed into ``caps.near`` slots (Gaussian 0 in the
        slots past their count, masked by ``near_valid``); their count stays on the
        device (``caps.near_count``): past the capacity, records are missing."""
        U, caps = mi.UInt32, self.caps
        if near is None:
            caps.near_count = dr.zeros(U, 1)
            dr.eval(caps.near_count)
            return U()
        flag = U(near)
        caps.near_count = dr.sum(flag)
        if not caps.near:
            dr.eval(caps.near_count)
            return U()
        pos = dr.prefix_sum(flag)
        ids = dr.zeros(U, caps.near)
        dr.scatter(ids, dr.arange(U, n), pos, active=near & (pos < caps.near))
        self.near_valid = dr.arange(U, caps.near) < caps.near_count
        dr.eval(ids, self.near_valid, caps.near_count)
        return ids

    def near_lanes(self, nv: int):
        """(rec, row, valid): every detector row of each near slot (a recorded step's)."""
        U = mi.UInt32
        lane = dr.arange(U, self.caps.near * nv)
        rec = lane // nv
        row = mi.Int32(lane - rec * nv)
        valid = dr.gather(mi.Bool, self.near_valid, rec)
        dr.eval(rec, row, valid)
        return [(rec, row, valid)]

    def _capacity_lanes(self, n_rows, capacity: int):
        """(rec, row, valid) for ``capacity`` lanes: the first sum(n_rows) are the records'
        rows, the rest invalid (their records' last segment is exhausted there). The row
        total stays on the device (``caps.rows_total``): past the capacity rows are
        missing."""
        U = mi.UInt32
        self.caps.rows_total = total = dr.sum(n_rows)
        rec, offset = segment_lanes(n_rows, 0, capacity)
        valid = offset < dr.gather(U, n_rows, rec)
        row = mi.Int32(offset) + dr.gather(mi.Int32, self.footprint["row_lo"], rec)
        dr.eval(rec, row, valid, total)
        return rec, row, valid


class RowCapacity:
    """What a recorded training step fixes in advance: the (record, row) lanes of the
    regular records and the near-source record slots. The chunk leaves the counts it
    needed (mi.UInt32 [1], on the device) in ``rows_total`` and ``near_count``."""

    def __init__(self, rows: int, near: int):
        self.rows, self.near = int(rows), int(near)
        self.rows_total = self.near_count = None


def view_base(vi, det, v0=0, view=None):
    """Flat index of pixel (0, 0) of each record's view in an image that starts at view v0;
    an opaque scalar where all records are in one ``view`` (no per-lane gather)."""
    if view is not None:
        return dr.opaque(mi.Int32, (view - v0) * det.npix_py)
    return (vi - v0) * det.npix if v0 else vi * det.npix
