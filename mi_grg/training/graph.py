"""The Gaussian graph of GR-Gaussian (paper Sec. 3.2): mutual edges of the exact kNN
(``mi_grg.training.knn``), weights, the graph-augmented density multiplier, the Laplacian
loss and the PGA term.

Everything heavy is Dr.Jit-vectorised and runs unchanged on ``llvm_ad_mono`` and
``cuda_ad_mono`` (types are looked up at call time).

Conventions (used consistently by every function here)
------------------------------------------------------
* ``knn`` rows: neighbours of point i are entries ``i*k .. i*k+k-1``, sorted by distance,
  self excluded. A point with fewer than k other points (N <= k) has its missing entries
  padded with its OWN index and distance ``+inf``; ``mutual_edges`` drops them (j == i).
* Edge set E (paper Eq. 6): (i, j) with j in kNN(i) AND i in kNN(j). ``mutual_edges``
  stores each undirected edge ONCE, with ``src < dst``. Every per-node sum below applies
  an edge to both of its ends, i.e. sum_{j in N(i)} runs over all mutual neighbours of i.
* Weights w_ij = exp(-|p_i - p_j|^2 / s) (paper Eq. 9, whose "k" we call s). They are
  constants between graph rebuilds (training rebuilds after each densification): no
  gradient flows from them to the positions.

Units: positions in scene units, squared distances and s in scene units squared.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from mi_grg.training.knn import MAX_K, GraphError, check_k, check_points, knn  # noqa: F401

_EXP_CUTOFF = 87.0    # exp(-x) underflows float32 below ~-87


def _width(x) -> int:
    return dr.width(x) if x is not None else 0


# ---------------------------------------------------------------------------- edges
def mutual_edges(idx, k: int):
    """The paper's edge set E: (i, j) with j in kNN(i) and i in kNN(j).

    Args:
        idx: mi.UInt32 [N*k] from ``knn`` (padding entries j == i are ignored).
        k: the k used for ``idx``.

    Returns:
        (src, dst) mi.UInt32 [E], each undirected edge ONCE with src < dst.
    """
    k = check_k(k)
    total = _width(idx)
    if total % k:
        raise GraphError(f"idx must have N*k entries (k={k}), got {total}")
    n = total // k
    if n == 0:
        return dr.zeros(mi.UInt32, 0), dr.zeros(mi.UInt32, 0)
    if not bool(dr.all(idx < dr.opaque(mi.UInt32, n))[0]):   # opaque: N changes per rebuild
        raise GraphError(f"idx entries must be < N = {n}")
    e = dr.arange(mi.UInt32, total)
    i = e // k
    j = mi.UInt32(idx)
    valid = (j != i) & (i < j)      # i < j: each undirected edge from one end only
    back = dr.full(mi.Bool, False, total)
    for t in range(k):
        back |= dr.gather(mi.UInt32, idx, j * k + t, valid) == i
    keep = dr.compress(valid & back)
    return dr.gather(mi.UInt32, i, keep), dr.gather(mi.UInt32, j, keep)


def edge_weights(points, src, dst, s: float):
    """w_ij = exp(-|p_i - p_j|^2 / s) per edge (paper Eq. 9, where s is called k).

    Args:
        points: mi.Point3f [N] (scene units); src, dst: mi.UInt32 [E]; s > 0 (units^2).
    Returns:
        mi.Float [E], detached (weights are constants between graph rebuilds); exact 0
        where the exponent is below -87 (float32 underflow).
    """
    s = float(s)
    if not (math.isfinite(s) and s > 0):
        raise GraphError(f"s must be a finite squared length > 0 (scene units^2), got {s}")
    p = check_points(points)
    if _width(src) != _width(dst):
        raise GraphError(f"src [E] and dst [E] differ in length: {_width(src)} vs {_width(dst)}")
    if _width(src) == 0:
        return dr.zeros(mi.Float, 0)
    d = dr.gather(mi.Point3f, p, src) - dr.gather(mi.Point3f, p, dst)
    x = dr.squared_norm(d) / dr.opaque(mi.Float, s)   # s changes per rebuild: not a literal
    return dr.select(x < _EXP_CUTOFF, dr.exp(-x), 0.0)


# ---------------------------------------------------------------------------- graph
@dataclass
class Graph:
    """Mutual-kNN graph over N Gaussians. src/dst mi.UInt32 [E] (each undirected edge once,
    src < dst), weights mi.Float [E] (constants), k neighbours searched, s the weight
    scale (scene units^2), n the number of nodes."""

    src: object
    dst: object
    weights: object
    k: int
    s: float
    n: int
    #: (D, nbr, w): ``neighbour_table``'s rows, built on first use
    table: object = field(default=None, repr=False, compare=False)

    @property
    def num_edges(self) -> int:
        return _width(self.src)


def default_scale(dist2, k: int) -> float:
    """s = median over points of the squared distance to their k-th neighbour.

    Why: w = exp(-d^2 / s) is then ~e^-1 at a typical k-th neighbour and closer to 1 for
    nearer ones, whatever the scene units or the Gaussian count (the paper's literal
    s = k = 6 would give w ~ 1 for every edge in normalised [-1, 1]^3 scenes). The median
    ignores sparse outliers. Points without k neighbours (N <= k) use their farthest one;
    if no finite positive distance exists, s = 1."""
    k = check_k(k)
    n = _width(dist2) // k
    if n == 0:
        return 1.0
    d = mi.Float(dist2)
    # farthest finite neighbour of each point (the k-th unless padded)
    far = dr.full(mi.Float, -1.0, n)
    rows = dr.arange(mi.UInt32, n) * k
    for t in range(k):
        v = dr.gather(mi.Float, d, rows + t)
        far = dr.select(dr.isfinite(v), v, far)
    sel = dr.compress(far > 0)
    if dr.width(sel) == 0:
        return 1.0
    return float(dr.median(dr.gather(mi.Float, far, sel))[0])


def build_graph(points, k: int = 6, s: float | None = None) -> Graph:
    """kNN -> mutual edges -> weights. Rebuild after every densification step.

    Args:
        points: mi.Point3f [N] Gaussian centres (scene units).
        k: neighbours searched per point (paper: 6).
        s: weight scale in scene units^2; None -> ``default_scale``."""
    p = check_points(points)
    idx, d2 = knn(p, k)
    src, dst = mutual_edges(idx, k)
    if s is None:
        s = default_scale(d2, k)
    w = edge_weights(p, src, dst, s)
    dr.eval(src, dst, w)
    return Graph(src=src, dst=dst, weights=w, k=k, s=float(s), n=dr.width(p))


def _check_values(graph: Graph, values, name: str):
    if _width(values) != graph.n or not isinstance(values, mi.Float):
        raise GraphError(f"{name} must be mi.Float [N] with N = {graph.n} (one per Gaussian), "
                         f"got {type(values).__name__} of width {_width(values)}")
    return values


def _to_both_ends(graph: Graph, value_at_src, value_at_dst):
    """out[i] = sum over edges with src == i of value_at_src + those with dst == i of
    value_at_dst (differentiable)."""
    out = dr.zeros(mi.Float, graph.n)
    if graph.num_edges:
        # Local, not the LLVM default Expand, whose per-thread copies put N in the kernel
        # (a new kernel at every rebuild, since N changes with densification)
        dr.scatter_add(out, value_at_src, graph.src, mode=dr.ReduceMode.Local)
        dr.scatter_add(out, value_at_dst, graph.dst, mode=dr.ReduceMode.Local)
    return out


def neighbour_sum(graph: Graph, values):
    """sum_{j in N(i)} w_ij values_j for every node i: mi.Float [N] (differentiable in values)."""
    v = _check_values(graph, values, "values")
    if not graph.num_edges:
        return v * 0
    w = graph.weights
    return _to_both_ends(graph, w * dr.gather(mi.Float, v, graph.dst),
                         w * dr.gather(mi.Float, v, graph.src))


def degree(graph: Graph):
    """Number of mutual neighbours |N(i)| <= k of every node: mi.UInt32 [N]."""
    out = dr.zeros(mi.UInt32, graph.n)
    if graph.num_edges:
        dr.scatter_reduce(dr.ReduceOp.Add, out, mi.UInt32(1), graph.src, mode=dr.ReduceMode.Local)
        dr.scatter_reduce(dr.ReduceOp.Add, out, mi.UInt32(1), graph.dst, mode=dr.ReduceMode.Local)
    return out


def graph_density_scale(graph: Graph):
    """1 + sum_{i: j in N(i)} w_ij for every node j: mi.Float [N] (no gradient).

    The graph-augmented field (paper Eqs. 10, 13) sum_i [rho_i G_i + sum_{j in N(i)} w_ij
    rho_j G_j] equals sum_j rho_j (1 + sum_{i: j in N(i)} w_ij) G_j: each kernel's density
    is scaled by this factor. E is symmetric, so the sum is j's weighted degree."""
    w = graph.weights
    return 1.0 + _to_both_ends(graph, w, w)


def neighbour_table(graph: Graph):
    """Every node's mutual neighbours as D rows of N (D = the largest degree, <= k for
    ``build_graph``'s graphs): (D, nbr mi.UInt32 [D*N], w mi.Float [D*N]), entry m*N + i
    the m-th neighbour of i and its weight; unused entries hold i itself at weight 0.
    Per-node sums then need gathers only: a scatter-add over the edges, which the LLVM
    backend resolves lane by lane, was a visible share of the Laplacian's gradient on
    every training iteration. Built once per graph (cached on it)."""
    if graph.table is None:
        n, UInt32 = graph.n, mi.UInt32
        count = dr.zeros(UInt32, n)
        D, nbr, w = 0, dr.zeros(UInt32, 0), dr.zeros(mi.Float, 0)
        if graph.num_edges:
            # slot of each edge in both of its ends' rows (order within a row is free)
            slot_src = dr.scatter_inc(count, graph.src)
            dr.eval(slot_src)
            slot_dst = dr.scatter_inc(count, graph.dst)
            dr.eval(slot_dst, count)
            D = int(dr.max(count)[0])
            nn = dr.opaque(UInt32, n)            # N changes per rebuild: not a literal
            nbr = dr.arange(UInt32, D * n) % nn
            w = dr.zeros(mi.Float, D * n)
            for node, other, slot in ((graph.src, graph.dst, slot_src),
                                      (graph.dst, graph.src, slot_dst)):
                dr.scatter(nbr, other, slot * nn + node)
                dr.scatter(w, graph.weights, slot * nn + node)
            dr.eval(nbr, w)
        graph.table = (D, nbr, w)
    return graph.table


class _LaplacianOp(dr.CustomOp):
    """raw = sum_i sum_{j in N(i)} w_ij (rho_i - rho_j)^2 and its derivative
    4 sum_{j in N(i)} w_ij (rho_i - rho_j), per node from ``neighbour_table`` (no scatter)."""

    def eval(self, rho, graph):
        self.rho, self.graph = rho, graph
        diff = (dr.gather(mi.Float, rho, graph.src) - dr.gather(mi.Float, rho, graph.dst))
        return 2 * dr.sum(graph.weights * diff * diff)

    def _gradient(self):
        D, nbr, w = neighbour_table(self.graph)
        i = dr.arange(mi.UInt32, self.graph.n)
        nn = dr.opaque(mi.UInt32, self.graph.n)
        acc = dr.zeros(mi.Float, self.graph.n)
        for m in range(D):
            e = m * nn + i
            acc += dr.gather(mi.Float, w, e) * (self.rho - dr.gather(
                mi.Float, self.rho, dr.gather(mi.UInt32, nbr, e)))
        return 4 * acc

    def backward(self):
        self.set_grad_in("rho", self._gradient() * self.grad_out())

    def forward(self):
        self.set_grad_out(dr.sum(self._gradient() * self.grad_in("rho")))

    def name(self):
        return "laplacian"


def laplacian_loss(graph: Graph, densities, normalise: bool = True):
    """Graph Laplacian regulariser (paper Eq. 17), differentiable in densities.

    raw = sum_i sum_{j in N(i)} w_ij (rho_i - rho_j)^2  (each undirected edge counted twice,
    as in the paper) = 2 rho^T L rho with L = D - W.

    normalise=True (default) returns raw / sum_i sum_{j in N(i)} w_ij, the weighted mean
    squared density difference over edges, whose size does not grow with N or change with
    s. The paper's weight converts as lambda_ours = lambda_paper * (sum of weights) (e.g.
    about 8e-4 * 4 * 50k for their 50k Gaussians). normalise=False returns raw.
    Returns mi.Float [1]; 0 when the graph has no edges."""
    rho = _check_values(graph, densities, "densities")
    if not graph.num_edges:
        # zero, but still attached to rho so that dr.backward(loss) works (opaque: a literal
        # 0 would be simplified away together with the AD edge)
        return dr.sum(rho * dr.opaque(mi.Float, 0.0))
    neighbour_table(graph)   # before dr.custom, which hands the op a copy of the graph
    raw = dr.custom(_LaplacianOp, rho, graph)
    if not normalise:
        return raw
    return raw / dr.maximum(2 * dr.sum(graph.weights), 1e-30)


def mean_abs_density_difference(graph: Graph, densities):
    """PGA term (paper Eq. 15): (1/k) sum_{j in N(i)} |rho_i - rho_j|, mi.Float [N].

    Divided by the k searched, as in the paper, also for nodes with fewer than k mutual
    neighbours: their term is (|N(i)| / k) times their mean difference, and isolated nodes
    get 0 (a weakly connected node gets a weaker push to split). Unweighted (the paper
    uses plain |rho_i - rho_j|). A densification statistic: computed detached."""
    rho = dr.detach(_check_values(graph, densities, "densities"))
    if not graph.num_edges:
        return dr.zeros(mi.Float, graph.n)
    a = dr.abs(dr.gather(mi.Float, rho, graph.src) - dr.gather(mi.Float, rho, graph.dst))
    return _to_both_ends(graph, a, a) / graph.k
