"""The Gaussian graph (mi_grg.training.graph) against independent references: scipy's cKDTree in
float64, Python set constructions, dense NumPy matrices (W, L = D - W) and finite
differences."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import mi_grg  # noqa: F401  (sets up LLVM before mitsuba/drjit)
import drjit as dr
import mitsuba as mi

from mi_grg.training import graph as G
from mi_grg.training import knn as K


# ---------------------------------------------------------------------------- clouds
def uniform(rng, n):
    return rng.random((n, 3)).astype(np.float32)


def clustered(rng, n):
    """95% of the points in 4 tiny clusters of very different sizes, 5% sparse outliers."""
    nc = int(0.95 * n)
    centres = rng.random((4, 3))
    sigma = np.array([1e-4, 3e-4, 1e-3, 3e-3])
    lab = rng.integers(0, 4, nc)
    a = centres[lab] + rng.normal(size=(nc, 3)) * sigma[lab, None]
    return np.concatenate([a, rng.random((n - nc, 3))]).astype(np.float32)


def shell(rng, n):
    v = rng.normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def line(rng, n):
    t = rng.random(n)
    return (np.array([0.2, -0.5, 0.3]) + t[:, None] * np.array([1.0, 2.0, -0.5])).astype(np.float32)


def duplicated(rng, n):
    """Groups of coincident points (up to 40 copies) plus distinct ones."""
    base = rng.random((n // 10, 3))
    reps = rng.integers(1, 40, len(base))
    pts = np.repeat(base, reps, axis=0)[: n - n // 4]
    return rng.permutation(np.concatenate([pts, rng.random((n - len(pts), 3))])).astype(np.float32)


def offset(rng, n):
    """A 1e-3 cube at 500: float32 quantises it to ~30 values per axis (many exact ties)."""
    return (500 + 1e-3 * rng.random((n, 3))).astype(np.float32)


def tiny(rng, n):
    """Extent 1e-6 around the origin, plus a clustered part: scale independence."""
    return (1e-6 * np.concatenate([uniform(rng, n // 2), clustered(rng, n - n // 2)])
            ).astype(np.float32)


CLOUDS = {"uniform": uniform, "clustered": clustered, "shell": shell, "line": line,
          "duplicated": duplicated, "offset": offset, "tiny": tiny}


# ---------------------------------------------------------------------------- reference
def reference_knn(P, k):
    """float64 cKDTree on the float32 points: (sorted dist2 [N, k], index sets, tie-free mask).
    Self is removed by index (with duplicates it need not come first)."""
    P64 = P.astype(np.float64)
    n = len(P)
    kk = min(k + 2, n)
    d, i = cKDTree(P64).query(P64, kk)
    d, i = d.reshape(n, kk) ** 2, i.reshape(n, kk)
    rows = []
    for r in range(n):
        keep = i[r] != r
        rows.append((d[r][keep][: k + 1], i[r][keep][: k + 1]))
    m = min(k, n - 1)
    ref_d = np.full((n, k), np.inf)
    ref_d[:, :m] = np.array([dd[:m] for dd, _ in rows]).reshape(n, m)
    sets = [set(ii[:m].tolist()) for _, ii in rows]
    # rows whose k-th and (k+1)-th distances are clearly apart: the kNN set is unique
    if n - 1 > k:
        nxt = np.array([dd[k] for dd, _ in rows])
        scale = np.maximum(ref_d[:, k - 1], 1e-12)
        unique = nxt - ref_d[:, k - 1] > 1e-5 * scale + 1e-12
    else:
        unique = np.ones(n, bool)
    return ref_d, sets, unique


def check_knn(P, k, idx, d2):
    n = len(P)
    I = np.asarray(idx, dtype=np.int64).reshape(n, k)
    D = np.asarray(d2, dtype=np.float64).reshape(n, k)
    ref_d, ref_sets, unique = reference_knn(P, k)
    m = min(k, n - 1)
    # distances: sorted, and equal to the brute-force k smallest (float32 rounding)
    assert np.all(np.diff(D[:, :m], axis=1) >= 0)
    # differences of float32 coordinates carry a relative error <= 2^-24, so does d^2
    ext2 = float(np.ptp(P, axis=0).max()) ** 2 if n > 1 else 1.0
    tol = 2e-6 * ref_d[:, :m] + 1e-12 * ext2
    np.testing.assert_array_less(np.abs(D[:, :m] - ref_d[:, :m]), tol + 1e-30)
    # every listed neighbour is another point at the listed distance, none twice
    rows = np.arange(n)[:, None]
    assert np.all(I[:, :m] != rows)
    true = ((P[I[:, :m]].astype(np.float64) - P[:, None].astype(np.float64)) ** 2).sum(-1)
    np.testing.assert_array_less(np.abs(true - D[:, :m]), tol + 1e-30)
    for r in range(n):
        assert len(set(I[r, :m].tolist())) == m
    # tie-free rows: identical neighbour sets
    bad = [r for r in np.flatnonzero(unique) if set(I[r, :m].tolist()) != ref_sets[r]]
    assert not bad, f"{len(bad)} rows differ from cKDTree, e.g. row {bad[0]}"
    # padding when N <= k
    if m < k:
        assert np.all(I[:, m:] == rows) and np.all(np.isinf(D[:, m:]))
    return I, D


# ---------------------------------------------------------------------------- kNN
@pytest.mark.parametrize("cloud", sorted(CLOUDS))
@pytest.mark.parametrize("k", [1, 6, 8])
def test_knn_matches_ckdtree(variant, rng, cloud, k):
    P = CLOUDS[cloud](rng, 3000)
    idx, d2, stats = K.knn_with_stats(mi.Point3f(*[mi.Float(P[:, a]) for a in range(3)]), k)
    assert dr.width(idx) == 3000 * k and isinstance(idx, mi.UInt32)
    assert isinstance(d2, mi.Float)
    check_knn(P, k, idx, d2)


def test_knn_clustered_uses_many_levels_and_fallback(rng):
    """The clustered cloud needs several cell sizes and exercises the certificate."""
    P = clustered(rng, 6000)
    idx, d2, stats = K.knn_with_stats(P, 6)
    check_knn(P, 6, idx, d2)
    assert len(stats["start_levels"]) >= 4, stats
    assert stats["failed_certificates"] > 0, stats


def _adversarial():
    """A level-3 grid (h = H / 8 with H ~ 1): query Q at a cell centre, k = 6 points near the
    corners of its 3x3x3 block (distance 2.42 h) and one point just outside a block face
    (distance 1.6 h). A 3x3x3 search at that level misses the true nearest neighbour."""
    H = 1.0 * (1 + 2.0 ** -10)
    h = H / 8
    q = np.array([3.5, 3.5, 3.5]) * h
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    pts = [np.zeros(3), np.ones(3), q, q + np.array([1.6 * h, 0, 0])]
    pts += [q + 1.4 * h * c for c in corners[:6]]
    return np.array(pts, np.float32), 2  # index of Q


def test_single_level_search_is_wrong_and_certificate_catches_it():
    P, qi = _adversarial()
    p = mi.Point3f(*[mi.Float(P[:, a]) for a in range(3)])
    frame = K._Frame(p)
    lv = frame.level(3)
    lv["delta"] = frame.delta
    bd, bi, cert, _ = K._query_level(p, mi.UInt32([qi]), lv, K._build_level(p, lv), 6)
    found = {int(b[0]) for b in bi}
    assert 3 not in found                      # the 3x3x3 search alone is wrong ...
    assert not bool(cert[0])                   # ... and the certificate says so
    # the full search, started on that level, falls back to coarser ones and is exact
    idx, d2, stats = K.knn_with_stats(P, 6, start_level=3)
    I, _ = check_knn(P, 6, idx, d2)
    assert I[qi, 0] == 3
    assert stats["start_levels"] == {3: len(P)} and stats["failed_certificates"] >= 1


@pytest.mark.parametrize("r", [2, 3, 4, 5])
def test_certificate_is_sound_at_every_level(rng, r):
    """Single-level searches at fixed cell sizes: every certified row equals brute force,
    and at coarse-enough-to-matter levels some rows are uncertified AND wrong."""
    P = np.concatenate([uniform(rng, 1500), clustered(rng, 1500)])
    k = 6
    p = mi.Point3f(*[mi.Float(P[:, a]) for a in range(3)])
    frame = K._Frame(p)
    lv = frame.level(r)
    lv["delta"] = frame.delta
    n = len(P)
    bd, bi, cert, _ = K._query_level(p, dr.arange(mi.UInt32, n), lv, K._build_level(p, lv), k)
    D = np.stack([np.asarray(b, np.float64) for b in bd], 1)
    cert = np.asarray(cert)
    ref_d, _, _ = reference_knn(P, k)
    close = np.abs(D - ref_d) <= 1e-6 + 2e-6 * ref_d
    wrong = ~close.all(1)
    assert not np.any(wrong & cert), "a certified row is not exact"
    assert cert.sum() > 0
    if r >= 4:  # cells smaller than sparse points' k-th distances
        assert wrong.sum() > 0 and (~cert).sum() >= wrong.sum()


@pytest.mark.parametrize("n", [1, 2, 6, 7])
def test_knn_fewer_points_than_k_pads_with_self(variant, rng, n):
    P = uniform(rng, n)
    idx, d2 = K.knn(P, 6)
    check_knn(P, 6, idx, d2)


def test_knn_empty_and_errors():
    idx, d2 = K.knn(np.zeros((0, 3), np.float32), 6)
    assert dr.width(idx) == 0 and dr.width(d2) == 0
    bad = np.zeros((10, 3), np.float32)
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="points"):
        K.knn(bad, 6)
    with pytest.raises(ValueError, match="points"):
        K.knn(np.zeros((10, 2)), 6)
    with pytest.raises(ValueError, match="start_level"):
        K.knn_with_stats(np.zeros((10, 3)), 6, start_level=19)
    for k in (0, K.MAX_K + 1, 2.0):
        with pytest.raises(ValueError, match="k must"):
            K.knn(np.zeros((10, 3)), k)


def test_knn_all_points_identical():
    P = np.full((200, 3), 0.25, np.float32)
    idx, d2 = K.knn(P, 6)
    I = np.asarray(idx).reshape(200, 6)
    assert np.all(np.asarray(d2) == 0)
    assert np.all(I != np.arange(200)[:, None])
    assert all(len(set(r)) == 6 for r in I.tolist())


# ---------------------------------------------------------------------------- edges
def python_mutual(I):
    nbr = [set(r) for r in I.tolist()]
    return {(min(i, j), max(i, j)) for i in range(len(nbr)) for j in nbr[i]
            if j != i and i in nbr[j]}


@pytest.mark.parametrize("k", [1, 6, 8])
def test_mutual_edges_match_set_construction(variant, rng, k):
    P = np.concatenate([uniform(rng, 1000), clustered(rng, 1000)])
    idx, d2 = K.knn(P, k)
    I, _ = check_knn(P, k, idx, d2)
    src, dst = G.mutual_edges(idx, k)
    S, T = np.asarray(src, np.int64), np.asarray(dst, np.int64)
    assert np.all(S < T)
    got = set(zip(S.tolist(), T.tolist()))
    assert len(got) == len(S)                                  # each edge once
    assert got == python_mutual(I)
    # ... and from cKDTree directly (this cloud has no ties at the k-th neighbour)
    _, i = cKDTree(P.astype(np.float64)).query(P.astype(np.float64), k + 1)
    ref = np.array([[j for j in row if j != r][:k] for r, row in enumerate(i)])
    assert got == python_mutual(ref)
    if k == 1:
        assert len(got) > 0


def test_mutual_edges_ignore_padding_and_validate():
    P = np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0]], np.float32)
    idx, _ = K.knn(P, 6)               # every row padded with self
    src, dst = G.mutual_edges(idx, 6)
    got = set(zip(np.asarray(src).tolist(), np.asarray(dst).tolist()))
    assert got == {(0, 1), (0, 2), (1, 2)}
    with pytest.raises(ValueError, match="N\\*k"):
        G.mutual_edges(mi.UInt32([0, 1, 2]), 2)
    with pytest.raises(ValueError, match="< N"):
        G.mutual_edges(mi.UInt32([1, 5]), 1)


# ---------------------------------------------------------------------------- dense refs
def dense(graph, n):
    W = np.zeros((n, n))
    S, T = np.asarray(graph.src), np.asarray(graph.dst)
    w = np.asarray(graph.weights, np.float64)
    W[S, T] = w
    W[T, S] = w
    A = np.zeros((n, n))
    A[S, T] = A[T, S] = 1
    return W, A


@pytest.fixture
def small_graph(rng):
    P = np.concatenate([uniform(rng, 40), 0.5 + 0.01 * uniform(rng, 20)])
    return P, G.build_graph(P, k=4)


def test_default_scale_and_weights(small_graph):
    P, g = small_graph
    d, _ = cKDTree(P.astype(np.float64)).query(P.astype(np.float64), 5)
    kth = np.sort(d[:, 4] ** 2)
    assert g.s == pytest.approx(kth[(len(kth) - 1) // 2], rel=1e-5)   # lower median
    S, T = np.asarray(g.src), np.asarray(g.dst)
    P64 = P.astype(np.float64)
    ref = np.exp(-((P64[S] - P64[T]) ** 2).sum(1) / g.s)
    np.testing.assert_allclose(np.asarray(g.weights), ref, rtol=1e-5, atol=1e-7)
    assert g.n == 60 and g.k == 4 and g.num_edges == len(S) > 0
    # explicit s, underflow guard, validation
    w = np.asarray(G.edge_weights(P, g.src, g.dst, 1e-12))
    assert np.all(np.isfinite(w)) and np.all(w[((P64[S] - P64[T]) ** 2).sum(1) > 1e-9] == 0)
    for s in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="s must"):
            G.edge_weights(P, g.src, g.dst, s)


def test_neighbour_sum_density_scale_degree_vs_dense(variant, small_graph, rng):
    P, _ = small_graph
    g = G.build_graph(P, k=4)
    n = len(P)
    W, A = dense(g, n)
    v = rng.normal(size=n)
    vv = mi.Float(v.astype(np.float32))
    np.testing.assert_allclose(np.asarray(G.neighbour_sum(g, vv)), W @ v, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(G.graph_density_scale(g)), 1 + W.sum(0), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(G.degree(g)), A.sum(1))
    assert np.all(A.sum(1) <= 4)
    # gradient of <c, W v> w.r.t. v is W^T c
    c = rng.normal(size=n)
    dr.enable_grad(vv)
    dr.backward(dr.sum(mi.Float(c.astype(np.float32)) * G.neighbour_sum(g, vv)))
    np.testing.assert_allclose(np.asarray(dr.grad(vv)), W.T @ c, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="values"):
        G.neighbour_sum(g, mi.Float(np.zeros(n - 1, np.float32)))


def test_laplacian_vs_dense_matrix(variant, small_graph, rng):
    P, _ = small_graph
    g = G.build_graph(P, k=4)
    n = len(P)
    W, _ = dense(g, n)
    L = np.diag(W.sum(1)) - W
    rho = rng.random(n)
    quad = rho @ L @ rho                      # = sum over undirected edges w (ri - rj)^2
    r = mi.Float(rho.astype(np.float32))
    raw = float(G.laplacian_loss(g, r, normalise=False)[0])
    assert raw == pytest.approx(2 * quad, rel=1e-5)
    assert float(G.laplacian_loss(g, r)[0]) == pytest.approx(2 * quad / W.sum(), rel=1e-5)
    # AD gradient vs the dense formula: d(2 rho^T L rho) = 4 L rho
    for norm, scale in ((False, 1.0), (True, 1.0 / W.sum())):
        r = mi.Float(rho.astype(np.float32))
        dr.enable_grad(r)
        dr.backward(G.laplacian_loss(g, r, normalise=norm))
        np.testing.assert_allclose(np.asarray(dr.grad(r)), 4 * L @ rho * scale,
                                   rtol=1e-4, atol=1e-6 * scale)
    # ... and vs central finite differences of the function itself (float64 reference)
    def f(x):
        return float(G.laplacian_loss(g, mi.Float(x.astype(np.float32)), normalise=False)[0])
    grad = 4 * L @ rho
    for i in rng.choice(n, 5, replace=False):
        e = np.zeros(n)
        e[i] = 1e-2
        fd = (f(rho + e) - f(rho - e)) / 2e-2
        assert fd == pytest.approx(grad[i], rel=2e-2, abs=1e-3)
    # forward mode: d raw = <4 L rho, t>
    t = rng.normal(size=n)
    r = mi.Float(rho.astype(np.float32))
    dr.enable_grad(r)
    dr.set_grad(r, mi.Float(t.astype(np.float32)))
    out = G.laplacian_loss(g, r, normalise=False)
    dr.forward_to(out)
    assert float(dr.grad(out)[0]) == pytest.approx(float(grad @ t), rel=1e-4, abs=1e-6)
    # constant densities are not penalised
    assert float(G.laplacian_loss(g, mi.Float(np.full(n, 0.7, np.float32)))[0]) == \
        pytest.approx(0, abs=1e-9)


def test_neighbour_table_holds_each_nodes_mutual_neighbours(variant, small_graph, rng):
    """Row m of node i: its m-th neighbour and w_ij; unused entries i itself at weight 0.
    Also for a hand-made graph whose degree exceeds k (the table is as wide as needed)."""
    P, _ = small_graph
    star = G.Graph(src=mi.UInt32([0, 0, 0, 0, 0, 1]), dst=mi.UInt32([1, 2, 3, 4, 5, 2]),
                   weights=mi.Float([0.5, 0.25, 0.125, 1.0, 2.0, 4.0]), k=2, s=1.0, n=7)
    for g in (G.build_graph(P, k=4), star):
        n = g.n
        W, _ = dense(g, n)
        D, nbr, w = G.neighbour_table(g)
        nbr = np.asarray(nbr).reshape(D, n)
        w = np.asarray(w).reshape(D, n)
        assert D == int((W > 0).sum(1).max())
        for i in range(n):
            got = {int(j): float(x) for j, x in zip(nbr[:, i], w[:, i]) if x != 0}
            want = {j: float(W[i, j]) for j in np.nonzero(W[i])[0]}
            assert got == pytest.approx(want) and len(got) == len(want)
            assert all(nbr[m, i] == i for m in range(D) if w[m, i] == 0)
        rho = rng.random(n)
        L = np.diag(W.sum(1)) - W
        r = mi.Float(rho.astype(np.float32))
        dr.enable_grad(r)
        dr.backward(G.laplacian_loss(g, r, normalise=False))
        np.testing.assert_allclose(np.asarray(dr.grad(r)), 4 * L @ rho, rtol=1e-4, atol=1e-6)


def test_mean_abs_density_difference_vs_dense(variant, small_graph, rng):
    P, _ = small_graph
    g = G.build_graph(P, k=4)
    n = len(P)
    _, A = dense(g, n)
    rho = rng.random(n)
    ref = (A * np.abs(rho[:, None] - rho[None, :])).sum(1) / 4
    got = np.asarray(G.mean_abs_density_difference(g, mi.Float(rho.astype(np.float32))))
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)
    iso = A.sum(1) == 0
    assert np.all(got[iso] == 0)


def test_graph_without_edges():
    g = G.build_graph(np.array([[0, 0, 0]], np.float32), k=6)
    assert g.num_edges == 0 and g.n == 1 and g.s == 1.0
    r = mi.Float([0.5])
    dr.enable_grad(r)
    loss = G.laplacian_loss(g, r)
    dr.backward(loss)
    assert float(loss[0]) == 0 and float(dr.grad(r)[0]) == 0
    assert np.asarray(G.graph_density_scale(g)).tolist() == [1.0]
    assert np.asarray(G.mean_abs_density_difference(g, r)).tolist() == [0.0]
