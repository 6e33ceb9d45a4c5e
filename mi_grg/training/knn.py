"""Exact k nearest neighbours of a point cloud in Dr.Jit (the Gaussian graph's kNN).

Why our own search and not scipy's cKDTree: it runs as Dr.Jit kernels on the variant's
device, so on ``cuda_ad_mono`` the Gaussian centres never leave the GPU (cKDTree would
need a host round trip of the whole cloud at every graph rebuild), and the same code runs
on ``llvm_ad_mono``, where it is as fast as cKDTree or faster (bench/graph.py,
docs/bench/graph.md). Only scalars (the bounding box, counts) are read back.
Tests check it equals cKDTree's neighbours (up to ties).

``knn`` rows: neighbours of point i are entries ``i*k .. i*k+k-1``, sorted by distance,
self excluded; a point with fewer than k other points (N <= k) has its missing entries
padded with its OWN index and distance ``+inf``. Positions in scene units, squared
distances in scene units squared.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

MAX_K = 32            # neighbours are kept in registers: 2 k selects per candidate
_MAX_LEVEL = 18       # finest grid: H / 2^18 cells; float32 coordinates resolve ~2^-23 H
_EPS32 = 2.0 ** -23
_INF = float("inf")
_START_COUNT = 2      # start where the parent cell holds >= 2 (k + 1) points (see knn)
_HEAVY_CELL = 16      # a cell with > 16 (k + 1) points is scanned after the others


class GraphError(ValueError):
    """Invalid graph input; the message names the argument."""


# ---------------------------------------------------------------------------- helpers
def _scalar(x) -> float:
    """Python float of a width-1 Dr.Jit value (forces evaluation)."""
    return float(x[0])


def check_points(points):
    """Detached Point3f copy, with NaN/Inf rejected."""
    if not isinstance(points, mi.Point3f):
        # NumPy convenience: float array [N, 3]
        arr = np.asarray(points, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise GraphError(f"points must be mi.Point3f [N] or an array [N, 3], got "
                             f"{type(points).__name__} of shape {arr.shape}")
        points = mi.Point3f(*[mi.Float(np.ascontiguousarray(arr[:, a])) for a in range(3)])
    p = mi.Point3f(dr.detach(points))
    if dr.width(p) and not bool(dr.all(dr.isfinite(p.x) & dr.isfinite(p.y)
                                       & dr.isfinite(p.z))[0]):
        raise GraphError("points [N, 3] contain NaN or Inf")
    return p


def check_k(k) -> int:
    if not isinstance(k, (int,)) or isinstance(k, bool) or not 1 <= k <= MAX_K:
        raise GraphError(f"k must be an int in [1, {MAX_K}], got {k!r}")
    return k


def _hash_bucket(cx, cy, cz, mask):
    """Bucket of integer cell (cx, cy, cz) in a power-of-two hash table (mask = T - 1).
    Murmur3 finaliser over a linear mix: neighbouring cells spread over the table."""
    h = (mi.UInt32(cx) * 73856093) ^ (mi.UInt32(cy) * 19349663) ^ (mi.UInt32(cz) * 83492791)
    h ^= h >> 16
    h *= 0x85EBCA6B
    h ^= h >> 13
    h *= 0xC2B2AE35
    h ^= h >> 16
    return h & mask


def _bucket(cx, cy, cz, lv):
    """Bucket of a cell at a grid level: dense index on coarse levels, hash on fine ones."""
    if lv["dense"]:
        r = lv["res_u"]
        return mi.UInt32(cx) + r * (mi.UInt32(cy) + r * mi.UInt32(cz))
    return _hash_bucket(cx, cy, cz, lv["mask"])


def _cells(px, py, pz, lo, inv_h, res_i):
    """Grid coordinates u = (p - lo) / h and integer cells floor(u), clamped to the grid."""
    u = [(px - lo[0]) * inv_h, (py - lo[1]) * inv_h, (pz - lo[2]) * inv_h]
    c = [dr.clip(mi.Int32(dr.floor(a)), 0, res_i - 1) for a in u]
    return u, c


class _Frame:
    """The bounding cube shared by all grid levels, and the table size."""

    def __init__(self, p):
        n = dr.width(p)
        self.n = n
        self.lo = [_scalar(dr.min(c)) for c in (p.x, p.y, p.z)]
        hi = [_scalar(dr.max(c)) for c in (p.x, p.y, p.z)]
        ext = max(h - l for h, l in zip(hi, self.lo))
        # Cube side H slightly larger than the extent so floor(u) < 2^r never rounds out.
        self.H = ext * (1 + 2.0 ** -10) if ext > 0 else 1.0
        # Certificate slack: rounding of u = (p - lo)/h is <= ~2 eps32 H per coordinate,
        # for the query and for the candidate; 8 eps32 H covers both with room.
        self.delta = 8 * _EPS32 * self.H
        self.table = 1 << max(1, (2 * n - 1).bit_length())   # >= 2N buckets

    def level(self, r: int) -> dict:
        res = 1 << r
        dense = res ** 3 <= self.table
        return {"r": r, "res": res, "dense": dense,
                "size": res ** 3 if dense else self.table,
                "res_u": dr.opaque(mi.UInt32, res), "res_i": dr.opaque(mi.Int32, res),
                "mask": dr.opaque(mi.UInt32, self.table - 1),
                "inv_h": dr.opaque(mi.Float, res / self.H),
                "h": dr.opaque(mi.Float, self.H / res),
                "lo": [dr.opaque(mi.Float, v) for v in self.lo]}


def _morton(p, frame):
    """30-bit Morton code of each point on a 1024^3 grid over the bounding cube."""
    code = dr.zeros(mi.UInt32, dr.width(p))
    scale = dr.opaque(mi.Float, 1024 / frame.H)   # opaque: the frame changes per rebuild
    for a, x in enumerate((p.x, p.y, p.z)):
        v = mi.UInt32(dr.clip((x - dr.opaque(mi.Float, frame.lo[a])) * scale, 0, 1023))
        v = (v | (v << 16)) & 0x030000FF   # spread 10 bits to every third bit
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        v = (v | (v << 2)) & 0x09249249
        code |= v << a
    return code


def _bucket_of_points(p, lv):
    u, c = _cells(p.x, p.y, p.z, lv["lo"], lv["inv_h"], lv["res_i"])
    return u, c, _bucket(c[0], c[1], c[2], lv)


def _build_level(p, lv):
    """Counting sort of all points by bucket, stored as two packed record arrays (one
    cache line per bucket visit and per candidate):
    ``brec`` [size, 8] = lo.x lo.y lo.z hi.x | hi.y hi.z start end: tight bounding box of
    the bucket's points (empty: +inf..-inf) and its slot range (UInt32 bits);
    ``prec`` [N, 8] = p.x p.y p.z index | cell.x cell.y cell.z 0 per sorted slot (index
    and cells as UInt32/Int32 bits; the cell serves the exact same-cell test)."""
    n, size = dr.width(p), lv["size"]
    _, c, b = _bucket_of_points(p, lv)
    counts = dr.zeros(mi.UInt32, size + 1)
    slot = dr.scatter_inc(counts, b)
    dr.eval(slot)   # the atomic's result must be materialised before other use
    start = dr.prefix_sum(counts)            # exclusive; start[size] = N
    dest = (dr.gather(mi.UInt32, start, b) + slot) * 8
    prec = dr.zeros(mi.Float, 8 * n)
    as_f = lambda v: dr.reinterpret_array(mi.Float, v)  # noqa: E731
    for f, val in enumerate((p.x, p.y, p.z, as_f(dr.arange(mi.UInt32, n)),
                             as_f(c[0]), as_f(c[1]), as_f(c[2]))):
        dr.scatter(prec, val, dest + f)
    # The tight box lets pruning skip a far cluster that sits in a neighbouring cell,
    # which the cell's own extent could not.
    box = []
    for val in (p.x, p.y, p.z):
        lo = dr.full(mi.Float, _INF, size)
        dr.scatter_reduce(dr.ReduceOp.Min, lo, val, b)
        box.append(lo)
    for val in (p.x, p.y, p.z):
        hi = dr.full(mi.Float, -_INF, size)
        dr.scatter_reduce(dr.ReduceOp.Max, hi, val, b)
        box.append(hi)
    buckets = dr.arange(mi.UInt32, size)
    brec = dr.empty(mi.Float, 8 * size)
    for f, val in enumerate(box + [as_f(dr.gather(mi.UInt32, start, buckets)),
                                   as_f(dr.gather(mi.UInt32, start, buckets + 1))]):
        dr.scatter(brec, val, buckets * 8 + f)
    out = {"brec": brec, "prec": prec}
    dr.eval(out)
    return out


def _cell_counts(p, lv):
    """Number of points in each point's own cell at this level (hash collisions add a few)."""
    _, _, b = _bucket_of_points(p, lv)
    counts = dr.zeros(mi.UInt32, lv["size"])
    dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), b, mode=dr.ReduceMode.Local)
    return dr.gather(mi.UInt32, counts, b)


def _scan_candidate(grid, qp, qi, j, scan, tx, ty, tz, bd: list, bi: list, k: int):
    """Lanes with ``scan``: candidate j of the open cell (tx, ty, tz) enters the sorted
    register lists ``bd`` / ``bi`` (updated in place) if it is nearer. Returns the next j."""
    UInt32, Int32 = mi.UInt32, mi.Int32
    r0 = dr.gather(mi.Vector4f, grid["prec"], 2 * j, scan)       # p.xyz, index
    r1 = dr.gather(mi.Vector4f, grid["prec"], 2 * j + 1, scan)   # cell.xyz, 0
    cand = dr.reinterpret_array(UInt32, r0.w)
    same = (scan & (dr.reinterpret_array(Int32, r1.x) == tx)
            & (dr.reinterpret_array(Int32, r1.y) == ty)
            & (dr.reinterpret_array(Int32, r1.z) == tz) & (cand != qi))
    dx, dy, dz = r0.x - qp.x, r0.y - qp.y, r0.z - qp.z
    cd = dr.select(same, dr.fma(dx, dx, dr.fma(dy, dy, dz * dz)), _INF)
    ci = cand
    for s in range(k):  # insertion into the sorted register list
        sw = cd < bd[s]
        nd, ni = dr.select(sw, cd, bd[s]), dr.select(sw, ci, bi[s])
        cd, ci = dr.select(sw, bd[s], cd), dr.select(sw, bi[s], ci)
        bd[s], bi[s] = nd, ni
    return dr.select(scan, j + 1, j)


def _open_cell(grid, lv, qp, c, heavy, opening, cell, skipped, j, end, tx, ty, tz, dk):
    """Lanes with ``opening``: open the next neighbour cell (pass 1: (cell + 13) % 27, so
    offset 0,0,0 comes first; pass 2: the lowest deferred one), unless its bucket's box
    cannot beat the k-th distance ``dk``. Returns (cell, skipped, j, end, tx, ty, tz)."""
    UInt32, Int32 = mi.UInt32, mi.Int32
    res_i = lv["res_i"]
    pass1 = cell < 27
    cc = dr.select(pass1, (cell + 13) % 27, dr.tzcnt(skipped))
    bit = UInt32(1) << cc
    off = [Int32(cc % 3) - 1, Int32((cc // 3) % 3) - 1, Int32(cc // 9) - 1]
    nb = [c[a] + off[a] for a in range(3)]
    inside = (nb[0] >= 0) & (nb[0] < res_i) & (nb[1] >= 0) & (nb[1] < res_i) \
        & (nb[2] >= 0) & (nb[2] < res_i)
    b = _bucket(nb[0], nb[1], nb[2], lv)
    look = opening & inside
    # Skip buckets whose points' box cannot beat the current k-th distance. The gap is
    # a difference of floats (relative error <= eps), hence the relative slack.
    b0 = dr.gather(mi.Vector4f, grid["brec"], 2 * b, look)      # lo.xyz, hi.x
    b1 = dr.gather(mi.Vector4f, grid["brec"], 2 * b + 1, look)  # hi.yz, start, end
    gx = dr.maximum(dr.maximum(b0.x - qp.x, qp.x - b0.w), 0.0)
    gy = dr.maximum(dr.maximum(b0.y - qp.y, qp.y - b1.x), 0.0)
    gz = dr.maximum(dr.maximum(b0.z - qp.z, qp.z - b1.y), 0.0)
    look &= dr.fma(gx, gx, dr.fma(gy, gy, gz * gz)) * (1 - 1e-5) <= dk
    s0 = dr.reinterpret_array(UInt32, b1.z)
    s1 = dr.reinterpret_array(UInt32, b1.w)
    defer = look & pass1 & (s1 - s0 > heavy)
    take = look & ~defer
    j = dr.select(take, s0, j)
    end = dr.select(take, s1, end)
    tx = dr.select(opening, nb[0], tx)
    ty = dr.select(opening, nb[1], ty)
    tz = dr.select(opening, nb[2], tz)
    skipped = dr.select(defer, skipped | bit, skipped)
    skipped = dr.select(opening & ~pass1, skipped & ~bit, skipped)
    cell = dr.select(opening & pass1, cell + 1, cell)
    return cell, skipped, j, end, tx, ty, tz


def _query_level(p, q, lv, grid, k):
    """k nearest neighbours of points q (UInt32 indices) among the 27 cells around each one
    at one level, plus the certificate that the k-th distance is exact.

    Returns (dist2 list[k], idx list[k], certified Bool, loop iterations summed [1])."""
    qi = q
    qp = dr.gather(mi.Point3f, p, q)
    u, c = _cells(qp.x, qp.y, qp.z, lv["lo"], lv["inv_h"], lv["res_i"])
    res_i, h, delta = lv["res_i"], lv["h"], dr.opaque(mi.Float, lv["delta"])
    heavy = dr.opaque(mi.UInt32, _HEAVY_CELL * (k + 1))
    Float, UInt32, Int32 = mi.Float, mi.UInt32, mi.Int32
    m = dr.width(q)

    def cond(cell, skipped, j, end, tx, ty, tz, bd, bi, steps):
        # Pass 1 opens the 27 cells (centre first) but defers heavy ones (bit set in
        # `skipped`); pass 2 opens the deferred ones, by then mostly pruned by a good k-th
        # distance (sparse points next to dense clusters). Stop early when the k-th
        # distance is 0 (k coincident points: nothing can be closer; ties are allowed).
        return ((cell < 27) | (skipped != 0) | (j < end)) & (bd[k - 1] > 0)

    def body(cell, skipped, j, end, tx, ty, tz, bd, bi, steps):
        bd, bi = list(bd), list(bi)
        steps += 1
        # scan one candidate of the open cell, or open the next cell
        scan = j < end
        j = _scan_candidate(grid, qp, qi, j, scan, tx, ty, tz, bd, bi, k)
        cell, skipped, j, end, tx, ty, tz = _open_cell(grid, lv, qp, c, heavy, ~scan, cell,
                                                       skipped, j, end, tx, ty, tz, bd[k - 1])
        return cell, skipped, j, end, tx, ty, tz, tuple(bd), tuple(bi), steps

    state = (dr.zeros(UInt32, m), dr.zeros(UInt32, m), dr.zeros(UInt32, m), dr.zeros(UInt32, m),
             dr.zeros(Int32, m), dr.zeros(Int32, m), dr.zeros(Int32, m),
             tuple(dr.full(Float, _INF, m) for _ in range(k)),
             tuple(UInt32(qi) for _ in range(k)), dr.zeros(UInt32, m))
    *_, bd, bi, steps = dr.while_loop(state, cond, body, label="mi_grg.knn")

    # Certificate: every point outside the 3x3x3 block lies beyond one of its faces, so
    # its distance is >= the query's distance to that face. Faces with no grid cells
    # beyond them do not count. Exact if sqrt(d_k) + slack <= that distance.
    bound = dr.full(Float, _INF, m)
    for a in range(3):
        lower = dr.select(c[a] - 1 > 0, u[a] - Float(c[a] - 1), _INF)
        upper = dr.select(c[a] + 1 < res_i - 1, Float(c[a] + 2) - u[a], _INF)
        bound = dr.minimum(bound, dr.minimum(lower, upper))
    cert = dr.sqrt(bd[k - 1]) * (1 + 1e-6) + delta <= bound * h
    bd, bi = list(bd), list(bi)
    dr.eval(bd, bi, cert, steps)   # one kernel for the loop; else each later use re-runs it
    return bd, bi, cert, dr.sum(Float(steps))   # float: no UInt32 overflow on huge N


# ---------------------------------------------------------------------------- kNN
def knn_with_stats(points, k: int = 6, start_level: int | None = None):
    """``knn`` plus a dict of how the search went (see ``knn``). ``start_level`` (0 .. 18)
    forces every point to start on that grid level (diagnostics and tests); the result is
    exact whatever it is. Stats:
    ``start_levels`` {level: points starting there}, ``queries`` {level: points searched},
    ``failed_certificates`` (searches whose certificate failed, each retried one level
    coarser), ``brute_force`` (points searched at level 0, the whole cloud), ``steps``
    {level: loop iterations summed over its queries (27 cell visits + candidates each)}."""
    k = check_k(k)
    p = check_points(points)
    n = dr.width(p)
    if start_level is not None and not (isinstance(start_level, int)
                                        and 0 <= start_level <= _MAX_LEVEL):
        raise GraphError(f"start_level must be an int in [0, {_MAX_LEVEL}], got {start_level!r}")
    if n * k >= 2 ** 32:
        raise GraphError(f"points: N * k = {n * k} entries do not fit UInt32 indices")
    stats = {"n": n, "k": k, "start_levels": {}, "queries": {}, "failed_certificates": 0,
             "brute_force": 0, "steps": {}}
    if n == 0:
        return dr.zeros(mi.UInt32, 0), dr.zeros(mi.Float, 0), stats
    frame = _Frame(p)
    levels = {r: frame.level(r) for r in range(_MAX_LEVEL + 1)}
    for lv in levels.values():
        lv["delta"] = frame.delta
    # Work on the points in Morton order (1024^3 cube): queries taken in index order are
    # then spatially coherent (SIMD lanes and cache lines shared by neighbours). Results
    # are written back under the caller's labels through `perm`.
    perm = dr.argsort(_morton(p, frame))
    p = dr.gather(mi.Point3f, p, perm)
    dr.eval(p, perm)

    # Start level of each point: one finer than the finest level whose own cell holds
    # >= m points (cells of side 2h at the parent level lie inside the 3x3x3 block at the
    # start level, so the block holds >= m points). m = 2 (k + 1): in a locally uniform
    # cloud the k-th neighbour then lies within about one cell side h, which is what the
    # certificate needs; denser regions start on finer levels, sparse ones on coarser.
    m_min = _START_COUNT * (k + 1)
    start = dr.zeros(mi.UInt32, n)
    alive = dr.full(mi.Bool, True, n)
    for r in range(_MAX_LEVEL):
        alive &= _cell_counts(p, levels[r]) >= m_min
        start += dr.select(alive, mi.UInt32(1), mi.UInt32(0))
        dr.eval(start, alive)
        if not bool(dr.any(alive)[0]):
            break
    if start_level is not None:
        start = dr.full(mi.UInt32, start_level, n)
    level = mi.UInt32(start)
    first = dr.full(mi.Bool, True, n)

    out_i = dr.repeat(dr.arange(mi.UInt32, n), k)     # padding: self index
    out_d = dr.full(mi.Float, _INF, n * k)              # padding: +inf
    for r in range(_MAX_LEVEL, -1, -1):
        q = dr.compress(level == r)
        m = dr.width(q)
        if m == 0:
            continue
        lv = levels[r]
        grid = _build_level(p, lv)
        stats["queries"][r] = m
        n_first = int(dr.count(dr.gather(mi.Bool, first, q))[0])
        if n_first:
            stats["start_levels"][r] = n_first
        bd, bi, cert, steps = _query_level(p, q, lv, grid, k)
        stats["steps"][r] = int(steps[0])
        if r == 0:
            cert = dr.full(mi.Bool, True, m)   # one cell holds every point: exhaustive
            stats["brute_force"] = m
        rows = dr.gather(mi.UInt32, perm, q) * k
        for s in range(k):
            dr.scatter(out_d, bd[s], rows + s, cert)
            dr.scatter(out_i, dr.gather(mi.UInt32, perm, bi[s]), rows + s, cert)
        # failures go one level coarser (its block contains this block)
        dr.scatter(level, dr.select(cert, mi.UInt32(0xFFFFFFFF), mi.UInt32(max(r - 1, 0))), q)
        dr.scatter(first, False, q)
        dr.eval(out_d, out_i, level, first)
        stats["failed_certificates"] += (m - int(dr.count(cert)[0])) if r > 0 else 0
        del grid
    return out_i, out_d, stats


def knn(points, k: int = 6):
    """Exact k nearest neighbours of every point among the others.

    Args:
        points: mi.Point3f [N] positions (scene units), finite.
        k: neighbours per point, 1 <= k <= MAX_K.

    Returns:
        (idx mi.UInt32 [N*k], dist2 mi.Float [N*k]) row-major: neighbours of point i at
        i*k .. i*k+k-1, sorted by squared distance (scene units^2), self excluded. Ties
        (equal distances, e.g. duplicate points) are broken arbitrarily. If a point has
        fewer than k other points (N <= k) the missing entries hold its own index and
        +inf: every consumer masks j == i.

    Algorithm (equal to brute force up to ties, see the certificate):
        A hierarchy of uniform grids over the bounding cube of side H: level r has cells of
        side h_r = H / 2^r (r = 0 .. 18; level 0 is one cell holding every point). Each
        level is a counting sort of the points by cell (``dr.scatter_inc`` slots +
        ``dr.prefix_sum`` offsets; dense cell index while 8^r <= 2N, else a 2N-bucket
        spatial hash with an exact same-cell test), storing per bucket the tight bounding
        box of its points. Points are processed in Morton order (``dr.argsort``) so that
        neighbouring SIMD lanes search neighbouring cells.

        Cell size rule: each point starts one level finer than the finest level at which
        its own cell holds >= 2 (k + 1) points. In a locally uniform cloud that puts the
        k-th neighbour within about one cell side, so the 3x3x3 search usually certifies
        at once; clustered clouds get small cells inside the clusters and large ones
        between them (a single global cell size would make cluster points scan whole
        clusters).

        Search: the point visits the 3x3x3 cells around its own (own cell first) with a
        vectorised ``dr.while_loop``, keeping the k best in registers; a cell whose box
        cannot beat the current k-th distance is skipped, and cells with > 16 (k + 1)
        points are visited last (by then usually skipped: sparse points next to a dense
        cluster). k coincident points (distance 0) end the search early.

        Certificate: the result is exact when the k-th distance (plus a float32 rounding
        slack of 8 eps H) is <= the distance from the point to the nearest face of the
        3x3x3 block that has cells beyond it: every unvisited point lies beyond such a
        face. Points that fail (common in clustered clouds: the edge of a cluster, sparse
        outliers) are searched again one level coarser, whose block contains the finer
        one, down to level 0, a brute force over all points that needs no certificate.

        Cost: the 27 cell visits plus the candidates scanned, per point; a sparse point
        whose true neighbours include a dense cluster scans that cluster's cell
        (bench/graph.py measures it).
    """
    idx, d2, _ = knn_with_stats(points, k)
    return idx, d2
