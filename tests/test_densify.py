"""PGA densification (mi_grg.training.densify): bookkeeping, sampling, pruning, Adam surgery."""
import math

import numpy as np
import pytest

import mi_grg  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_grg.training.config import Densification
from mi_grg.training.densify import DensifyError, DensifyWindow, PGADensifier
from mi_grg.core.gaussians import Gaussians, inverse_covariance
from mi_grg.training.optim import Adam

BBOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])   # volume size 2: clone if s <= 0.2
TWO_PI_32 = (2 * math.pi) ** 1.5


def make_raw(pos, scales, dens, rots=None):
    return Gaussians.from_numpy(pos, scales, rots, dens).to_raw()


def phys(raw):
    return Gaussians.from_raw(raw).numpy()


def raw_np(raw):
    out = {}
    for k, v in raw.items():
        out[k] = (np.asarray(v, np.float32).reshape(-1, 1) if dr.depth_v(v) == 1
                  else np.stack([np.asarray(c, np.float32) for c in v], -1))
    return out


def mass(d):
    return d["densities"].astype(np.float64) * TWO_PI_32 * np.prod(
        d["scales"].astype(np.float64), axis=1)


def densifier(max_count=None, **cfg):
    cfg.setdefault("use_pga", False)
    config = Densification(**cfg)
    window = DensifyWindow.for_config(config)
    if max_count is not None:
        window.max_count = max_count
    return PGADensifier(config, seed=7, window=window)


def feed(dens, grads):
    dens.reset(len(grads))
    dens.accumulate(mi.Float(np.asarray(grads, np.float32)))


def rand_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ------------------------------------------------------------------ clone / split
def test_clone_halves_density_and_preserves_mass(variant, rng):
    n = 6
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    sc = rng.uniform(0.02, 0.19, (n, 3))     # max scale <= 0.2: clone
    rho = rng.uniform(0.05, 2.0, n)
    raw = make_raw(pos, sc, rho, rand_quats(rng, n))
    before = phys(raw)
    d = densifier()
    feed(d, np.full(n, 1e-3))
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    after = phys(out)
    assert info["n_clone"] == n and info["n_split"] == 0 and info["n_after"] == 2 * n
    np.testing.assert_allclose(mass(after).sum(), mass(before).sum(), rtol=1e-6)
    np.testing.assert_allclose(after["densities"][:n], 0.5 * before["densities"], rtol=1e-6)
    np.testing.assert_allclose(after["densities"][n:], 0.5 * before["densities"], rtol=1e-6)
    r0, r1 = raw_np(raw), raw_np(out)
    for k in ("positions", "raw_scales", "raw_rotations"):   # unchanged fields: bit-exact
        np.testing.assert_array_equal(r1[k][:n], r0[k])
        np.testing.assert_array_equal(r1[k][n:], r0[k])


def test_split_bookkeeping(variant, rng):
    n = 5
    pos = rng.uniform(-0.3, 0.3, (n, 3))
    sc = rng.uniform(0.05, 0.1, (n, 3))
    sc[:, 1] = 0.3                           # max scale > 0.2: split
    rho = rng.uniform(0.05, 2.0, n)
    raw = make_raw(pos, sc, rho, rand_quats(rng, n))
    before = phys(raw)
    d = densifier(bbox_margin=10.0)          # keep every child
    feed(d, np.full(n, 1e-3))
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    after = phys(out)
    assert info["n_split"] == n and info["n_clone"] == 0 and len(after["densities"]) == 2 * n
    for half in (slice(0, n), slice(n, 2 * n)):   # first children, then second children
        np.testing.assert_allclose(after["densities"][half], 0.5 * before["densities"], rtol=1e-6)
        np.testing.assert_allclose(after["scales"][half], before["scales"] / 1.6, rtol=1e-6)
        np.testing.assert_array_equal(raw_np(out)["raw_rotations"][half],
                                      raw_np(raw)["raw_rotations"])
    # documented: total mass of the two children = parent mass / 1.6^3 (not preserved)
    np.testing.assert_allclose(mass(after)[:n] + mass(after)[n:], mass(before) / 1.6 ** 3,
                               rtol=1e-5)
    assert not np.allclose(after["positions"][:n], after["positions"][n:])


def test_split_children_are_samples_of_the_parent(variant, rng):
    n = 20000
    p0 = np.array([0.1, -0.2, 0.05])
    s0 = np.array([0.25, 0.08, 0.15])
    q0 = rand_quats(rng, 1)[0]
    raw = make_raw(np.tile(p0, (n, 1)), np.tile(s0, (n, 1)), np.full(n, 1.0),
                   np.tile(q0, (n, 1)))
    d = densifier(bbox_margin=10.0)
    feed(d, np.full(n, 1.0))
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    x = phys(out)["positions"].astype(np.float64)
    assert x.shape == (2 * n, 3)
    g = Gaussians.from_numpy(p0[None], s0[None], q0[None], [1.0])
    inv = inverse_covariance(g.scales, g.rotations)
    cov = np.linalg.inv(np.array([[float(inv[i][j][0]) for j in range(3)] for i in range(3)]))
    m = 2 * n
    err_mean = x.mean(0) - p0
    assert np.all(np.abs(err_mean) < 5 * np.sqrt(np.diag(cov) / m))
    emp = np.cov(x.T)
    # entries of a sample covariance have std ~ sqrt((S_ii S_jj + S_ij^2) / m)
    tol = 5 * np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov ** 2) / m)
    assert np.all(np.abs(emp - cov) < tol), (emp, cov)
    # the two children of one parent are independent draws
    c = np.corrcoef(x[:n, 0], x[n:, 0])[0, 1]
    assert abs(c) < 5 / math.sqrt(n)


def test_deterministic_for_a_seed(variant, rng):
    n = 50
    raw = make_raw(rng.uniform(-0.5, 0.5, (n, 3)), np.full((n, 3), 0.3), np.ones(n))

    def run(seed):
        d = PGADensifier(Densification(use_pga=False, bbox_margin=10.0), seed=seed)
        feed(d, np.ones(n))
        return raw_np(d.densify_and_prune(raw, None, bbox=BBOX, iteration=600)[0])
    a, b, c = run(1), run(1), run(2)
    np.testing.assert_array_equal(a["positions"], b["positions"])
    assert not np.array_equal(a["positions"], c["positions"])


# ------------------------------------------------------------------ prune
def test_prune_removes_exactly_low_density_and_outside(variant, rng):
    n = 12
    pos = rng.uniform(-0.9, 0.9, (n, 3))
    pos[2] = [1.05, 0.0, 0.0]          # outside by 0.05
    pos[5] = [0.0, -1.3, 0.2]          # outside by 0.3
    pos[7] = [1.0, 1.0, -1.0]          # on the boundary: kept
    rho = rng.uniform(0.01, 1.0, n)
    rho[3] = 5e-6                       # below 1e-5
    rho[9] = 2e-5                       # above: kept
    raw = make_raw(pos, np.full((n, 3), 0.05), rho)
    d = densifier()
    feed(d, np.zeros(n))                # no candidates
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    keep = np.setdiff1d(np.arange(n), [2, 3, 5])
    assert info["n_after"] == keep.size and info["n_pruned"] == 3
    r0, r1 = raw_np(raw), raw_np(out)
    for k in r0:
        np.testing.assert_array_equal(r1[k], r0[k][keep])
    # a margin of 0.1 x the box size (0.2 here) keeps the one 0.05 outside
    d2 = densifier(bbox_margin=0.1)
    feed(d2, np.zeros(n))
    out2, _ = d2.densify_and_prune(raw, None, bbox=BBOX)
    np.testing.assert_array_equal(raw_np(out2)["raw_densities"],
                                  r0["raw_densities"][np.setdiff1d(np.arange(n), [3, 5])])


# ------------------------------------------------------------------ Adam surgery
def test_adam_moments_follow_the_gaussians(variant, rng):
    n = 9
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    sc = np.full((n, 3), 0.05)
    sc[[1, 4]] = 0.4                       # split
    rho = rng.uniform(0.1, 1.0, n)
    rho[6] = 1e-6                          # pruned
    raw = make_raw(pos, sc, rho)
    opt = Adam()
    for _ in range(3):
        g = {k: type(v)(*[mi.Float(rng.normal(size=n).astype(np.float32))
                          for _ in range(len(v))]) if dr.depth_v(v) > 1
             else mi.Float(rng.normal(size=n).astype(np.float32)) for k, v in raw.items()}
        raw = opt.step(raw, grads=g)
    m_old = {k: raw_np({k: st.m})[k] for k, st in opt.state.items()}
    v_old = {k: raw_np({k: st.v})[k] for k, st in opt.state.items()}
    grads = np.zeros(n)
    grads[[0, 1, 4, 8]] = 1e-3             # clone 0, 8; split 1, 4
    d = densifier(bbox_margin=10.0)
    feed(d, grads)
    out, info = d.densify_and_prune(raw, opt, bbox=BBOX)
    survivors = np.array([0, 2, 3, 5, 7, 8])     # 1, 4 split; 6 pruned
    n_new = 2 + 4                                 # 2 clone copies + 4 children
    assert info["n_after"] == survivors.size + n_new == opt.width()
    for k in m_old:
        m_new = raw_np({k: opt.state[k].m})[k]
        v_new = raw_np({k: opt.state[k].v})[k]
        np.testing.assert_array_equal(m_new[:survivors.size], m_old[k][survivors])
        np.testing.assert_array_equal(v_new[:survivors.size], v_old[k][survivors])
        assert np.all(m_new[survivors.size:] == 0) and np.all(v_new[survivors.size:] == 0)
        assert opt.state[k].step == 3
    # the optimiser accepts the new set
    g = {k: type(v)(*[dr.zeros(mi.Float, info["n_after"]) for _ in range(len(v))])
         if dr.depth_v(v) > 1 else dr.zeros(mi.Float, info["n_after"]) for k, v in out.items()}
    opt.step(out, grads=g)
    assert d.size == info["n_after"] and float(dr.sum(d.grad_accum)[0]) == 0.0


# ------------------------------------------------------------------ PGA, schedule, cap
def test_graph_term_triggers_split_of_large_low_gradient_kernel(variant, rng):
    # Gaussian 0: large (split size), low view gradient, very different from neighbours.
    n = 7
    pos = np.array([[0, 0, 0]] + [[0.3 * np.cos(a), 0.3 * np.sin(a), 0]
                                  for a in np.linspace(0, 2 * np.pi, n - 1, endpoint=False)])
    sc = np.full((n, 3), 0.05)
    sc[0] = 0.35
    rho = np.full(n, 0.1)
    rho[0] = 1.1
    raw = make_raw(pos, sc, rho)
    # graph term: mean |rho_i - rho_j| over each node's neighbours (star: 0 <-> all)
    nbrs = {0: list(range(1, n)), **{i: [0] for i in range(1, n)}}
    term = np.array([np.mean(np.abs(rho[i] - rho[nbrs[i]])) for i in range(n)])
    grads = np.full(n, 1e-5)                    # below tau_pos = 5e-5
    results = {}
    for use_graph in (False, True):
        d = PGADensifier(Densification(use_pga=use_graph, bbox_margin=10.0), seed=0)
        feed(d, grads)
        gt = mi.Float(term.astype(np.float32)) if use_graph else None
        results[use_graph] = d.densify_and_prune(raw, None, graph_term=gt, bbox=BBOX)[1]
    assert results[False]["n_split"] == 0 and results[False]["n_clone"] == 0
    # g_0 = 1e-5 + 1e-4 * 1.0 >= 5e-5; the small ones: 1e-5 + 1e-4 * 1.0 too -> clone
    assert results[True]["n_split"] == 1
    assert results[True]["n_clone"] == n - 1
    # lambda_g scales the effect: with lambda_g = 1e-5 only g = 2e-5 < tau: nothing
    d = PGADensifier(Densification(use_pga=True, lambda_g=1e-5), seed=0)
    feed(d, grads)
    info = d.densify_and_prune(raw, None, graph_term=mi.Float(term.astype(np.float32)),
                               bbox=BBOX)[1]
    assert info["n_split"] == 0 and info["n_clone"] == 0
    with pytest.raises(DensifyError, match="graph_term"):
        d.augmented_gradient(None)
    with pytest.raises(DensifyError, match="width"):
        d.augmented_gradient(mi.Float([1.0, 2.0]))


def test_schedule(variant, rng):
    d = PGADensifier(Densification(use_pga=False))
    sched = [it for it in range(0, 16001, 50) if d.is_densify_iteration(it)]
    assert sched == list(range(600, 15000, 100))
    n = 4
    raw = make_raw(rng.uniform(-0.5, 0.5, (n, 3)), np.full((n, 3), 0.05), np.ones(n))
    feed(d, np.full(n, 1.0))
    same, info = d.step(550, raw, None, bbox=BBOX)
    assert same is raw and not info["densified"]
    assert float(dr.sum(d.grad_accum)[0]) == pytest.approx(4.0)   # untouched
    out, info = d.step(700, raw, None, bbox=BBOX)
    assert info["densified"] and info["n_after"] == 2 * n


def test_cap_keeps_the_highest_gradients(variant, rng):
    n = 10
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    raw = make_raw(pos, np.full((n, 3), 0.05), np.ones(n))
    grads = rng.permutation(np.arange(1, n + 1)) * 1e-4
    d = densifier(max_count=14)
    feed(d, grads)
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    assert info["capped"] and info["n_clone"] == 4 and info["n_after"] == 14
    cloned = np.argsort(-grads)[:4]
    p_new = raw_np(out)["positions"][n:]
    p_exp = raw_np(raw)["positions"][np.sort(cloned)]
    np.testing.assert_array_equal(p_new, p_exp)
    # at the cap: nothing densified, pruning still applies
    d = densifier(max_count=10)
    feed(d, grads)
    info = d.densify_and_prune(raw, None, bbox=BBOX)[1]
    assert info["n_after"] == 10 and info["n_clone"] == 0


def test_accumulate_multi_view_visibility(variant, rng):
    n, views = 5, 3
    g = rng.uniform(0, 1, (views, n))
    vis = rng.random((views, n)) < 0.6
    vis[:, 4] = False                                  # never visible -> 0
    d = PGADensifier(Densification(use_pga=False))
    d.accumulate(mi.Float(g.reshape(-1).astype(np.float32)), mi.Bool(vis.reshape(-1)),
                 n_views=views)
    d.accumulate(mi.Float(g[0].astype(np.float32)), mi.Bool(vis[0]))   # one more view
    tot = (g * vis).sum(0) + g[0] * vis[0]
    cnt = vis.sum(0) + vis[0]
    ref = np.where(cnt > 0, tot / np.maximum(cnt, 1), 0.0)
    np.testing.assert_allclose(np.asarray(d.averaged_gradient()), ref, rtol=1e-6)
    with pytest.raises(DensifyError, match="Gaussians"):
        d.accumulate(mi.Float(np.zeros(6, np.float32)))
    with pytest.raises(DensifyError, match="bbox"):
        d.densify_and_prune(make_raw(np.zeros((n, 3)), np.full((n, 3), 0.1), np.ones(n)), None)


def test_from_train_config_and_graph_module(variant, rng):
    """Composition with mi_grg.training.config and mi_grg.training.graph."""
    from mi_grg.training import config, graph
    cfg = config.TrainConfig(densify=config.Densification(
        densify_interval=50, densify_start=100, densify_stop=1000, densify_grad_threshold=3e-5,
        lambda_g=2e-4, use_pga=True, max_gaussians=1234))
    d = PGADensifier(cfg.densify)           # the settings as written, and their window
    assert d.config is cfg.densify
    assert (d.window.interval, d.window.start, d.window.stop, d.window.max_count) == \
        (50, 100, 1000, 1234)
    assert d.is_densify_iteration(150) and not d.is_densify_iteration(125)
    n = 40
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    rho = np.where(pos[:, 0] > 0, 1.0, 0.1)          # a density edge at x = 0
    raw = make_raw(pos, np.full((n, 3), 0.05), rho)
    g = graph.build_graph(raw["positions"], k=6)
    term = graph.mean_abs_density_difference(g, Gaussians.from_raw(raw).densities)
    term_np = np.asarray(term)
    assert term_np.max() > 0 and term_np.min() == 0    # edge nodes vs interior nodes
    d = PGADensifier(Densification(use_pga=True), seed=0)
    feed(d, np.zeros(n))
    out, info = d.densify_and_prune(raw, None, graph_term=term, bbox=BBOX)
    # exactly the nodes with 1e-4 * term >= 5e-5 are cloned
    assert info["n_clone"] == int(np.sum(1e-4 * term_np.astype(np.float32) >= 5e-5))
    assert info["n_clone"] > 0


def _field(d, scale, x):
    """float64 sum_j rho_j scale_j G_j(x) for axis-aligned Gaussians (rotations identity)."""
    z = (x[:, None, :] - d["positions"][None].astype(np.float64)) / d["scales"][None]
    g = np.exp(-0.5 * np.sum(z * z, axis=2))
    return g @ (d["densities"].astype(np.float64) * np.asarray(scale, np.float64))


def test_rebuild_keeps_graph_field_through_clones(variant, rng):
    """Clones change neither positions nor the plain field; with carry_density_scale the
    graph field after the rebuild equals the one before (float64 reference), without it
    the clone pairs render more mass. ``source`` names each row's origin."""
    from mi_grg.training import graph
    from mi_grg.training.trainer import carry_density_scale
    n = 300
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    raw = make_raw(pos, np.full((n, 3), 0.04), rng.uniform(0.1, 1.0, n))
    m_old = graph.graph_density_scale(graph.build_graph(raw["positions"], k=6))
    d = densifier()
    chosen = rng.random(n) < 0.3
    feed(d, np.where(chosen, 1e-3, 0.0))
    out, info = d.densify_and_prune(raw, None, bbox=BBOX)
    assert info["n_clone"] == chosen.sum() and info["n_after"] == n + chosen.sum()
    source = np.asarray(info["source"])
    np.testing.assert_array_equal(source[:n], np.arange(n))
    np.testing.assert_array_equal(source[n:], np.flatnonzero(chosen))
    m_new = graph.graph_density_scale(graph.build_graph(out["positions"], k=6))
    x = rng.uniform(-0.6, 0.6, (500, 3))
    before = _field(phys(raw), m_old, x)
    carried = carry_density_scale(out, m_old, m_new, info["source"])
    assert dr.grad_enabled(carried["raw_densities"])
    np.testing.assert_allclose(_field(phys(carried), m_new, x), before, rtol=2e-5)
    plain = _field(phys(out), m_new, x)
    assert np.max(np.abs(plain / before - 1)) > 0.05      # the bias it removes
    for k in ("positions", "raw_scales", "raw_rotations"):   # only densities change
        np.testing.assert_array_equal(raw_np(carried)[k], raw_np(out)[k])




def test_densification_at_a_new_count_reuses_the_kernels(variant, rng, kernel_hashes):
    """Densify-and-prune, the Adam surgery and the graph built on the kNN (mutual edges,
    weights, PGA term, density scale, the Laplacian's forward and backward), run as
    training runs them (each round on the last round's output, N growing), trace the
    kernels of the earlier rounds: no count or weight scale enters a kernel as a literal
    (they did: 150 kernels compiled over the first 11 densifications of a 64^3 run, 1.1 s
    on the CPU). Checked by kernel hashes, whatever the cache holds. The kNN itself runs
    outside the check: which of its grid levels run depends on the points (its frame is
    checked by the next test)."""
    from mi_grg.training import graph
    n = 600
    raw = make_raw(rng.uniform(-0.6, 0.6, (n, 3)), rng.uniform(0.01, 0.3, (n, 3)),
                   rng.uniform(0.05, 1.0, n), rand_quats(rng, n))
    opt = Adam()
    d = PGADensifier(Densification(use_pga=True, densify_grad_threshold=0.9), seed=1,
                     window=DensifyWindow(max_count=10 ** 6))

    def round_(raw, idx, d2):
        for v in raw.values():
            dr.enable_grad(v)
        n = dr.width(raw["raw_densities"])
        src, dst = graph.mutual_edges(idx, 6)
        s = graph.default_scale(d2, 6)
        g = graph.Graph(src=src, dst=dst, weights=graph.edge_weights(raw["positions"], src, dst, s),
                        k=6, s=s, n=n)
        lap = graph.laplacian_loss(g, Gaussians.from_raw(raw).densities, normalise=False)
        dr.backward(dr.opaque(mi.Float, 1e-3) * lap)
        raw = opt.step(raw)
        term = graph.mean_abs_density_difference(g, Gaussians.from_raw(raw).densities)
        # gradients made on the device: a NumPy-mapped input's alignment (1 or 64 bytes,
        # as NumPy allocated it) would choose between two kernel variants by chance
        x = dr.arange(mi.Float, n) * dr.opaque(mi.Float, 0.618034) + dr.opaque(mi.Float, 0.1 * n)
        d.reset(n)
        d.accumulate(x - dr.floor(x))                     # spread over [0, 1)
        out, info = d.densify_and_prune(raw, opt, graph_term=term, bbox=BBOX)
        assert info["n_clone"] + info["n_split"] > 0
        dr.eval(graph.graph_density_scale(g), out)
        return out, info["n_after"]

    traced, counts = [], []
    for _ in range(4):
        idx, d2 = graph.knn(raw["positions"], 6)
        dr.eval(idx, d2)
        (raw, n_after), hashes = kernel_hashes(lambda: round_(raw, idx, d2))
        counts.append(n_after)
        traced.append(hashes)
    assert len(set(counts)) == len(counts), counts
    # at most one new fusion of equal-width work by coincidence (see test_fast_paths); the
    # old literals made a dozen new kernels every round
    new = [len(traced[k] - set().union(*traced[:k])) for k in range(2, len(traced))]
    assert sum(new) <= 1, f"rounds 2.. (N = {counts[2:]}) traced {new} kernel(s) not seen before"


def test_knn_in_another_frame_reuses_the_kernels(variant, rng, kernel_hashes):
    """The kNN of the same points moved and scaled (another bounding cube, as after a
    densification) traces the same kernels: the frame is not a literal (it was, in the
    Morton codes)."""
    from mi_grg.training.knn import knn
    p = rng.uniform(-0.6, 0.6, (500, 3))
    runs = []
    for scale, shift in ((1.0, 0.0), (1.25, 0.1), (0.8, -0.2)):
        q = mi.Point3f(*[mi.Float(np.ascontiguousarray(scale * p[:, a] + shift)) for a in range(3)])
        q = q + dr.opaque(mi.Float, 0.0)     # device memory, not a NumPy-mapped input
        dr.eval(q)
        (idx, _), hashes = kernel_hashes(lambda: knn(q, 6))
        runs.append((np.asarray(idx), hashes))
    assert all(np.array_equal(r[0], runs[0][0]) for r in runs)   # the same neighbours
    assert runs[2][1] <= runs[0][1] | runs[1][1], runs[2][1] - runs[0][1] - runs[1][1]


def test_demand_is_met_where_the_count_settled_below_the_cap():
    """densify.demand: the count's growth over the last quarter of the window (of the part
    run) and its share of the cap at the window's end, from the run's log."""
    from mi_grg.training.densify import DEMAND_CAP, DEMAND_GROWTH, DensifyWindow, demand
    w = DensifyWindow(start=100, stop=1100, interval=25, max_count=1000)

    def log(counts):    # iteration -> count, one row every 25 iterations to 2000
        return [{"iteration": it, "n_gaussians": counts(it), "loss": 0.0}
                for it in range(1, 2001, 25)]
    # settled: the count stops growing halfway through the window
    d = demand(log(lambda it: 300 + min(it, 600) // 2), w)
    assert d["met"] and d["growth"] == 0.0 and d["cap_share"] == pytest.approx(0.6)
    # still growing: the window ends at row 1076, its last quarter starts at 832 (row 826)
    d = demand(log(lambda it: 100 + 4 * min(it, 1100) // 10), w)
    n_end, n_q = 100 + 4 * 1076 // 10, 100 + 4 * 826 // 10
    assert d["growth"] == pytest.approx(n_end / n_q - 1) and d["growth"] > DEMAND_GROWTH
    assert not d["met"]
    # at the cap, although the count no longer grows
    d = demand(log(lambda it: min(1000, 500 + it)), w)
    assert d["growth"] == 0.0 and d["cap_share"] >= DEMAND_CAP and not d["met"]
    # a run stopped inside the window: its last quarter is that of the part run (rows to
    # 501; the quarter starts at 401, row 376)
    part = [r for r in log(lambda it: 100 + it // 2) if r["iteration"] <= 501]
    d = demand(part, w)
    assert d["growth"] == pytest.approx((100 + 501 // 2) / (100 + 376 // 2) - 1)
    # no row inside the window (a run that never densified), or rows without a count
    assert demand(log(lambda it: 5)[:3], w)["met"]
    assert demand([{"iteration": 500, "loss": 0.0}], w)["met"]
