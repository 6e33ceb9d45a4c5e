"""Adam (mi_grg.training.optim) against a float64 NumPy Adam written from the PyTorch formula."""
import math

import numpy as np
import pytest

import mi_grg  # noqa: F401  (sets up LLVM before drjit)
import drjit as dr
import mitsuba as mi

from mi_grg.training.optim import DEFAULT_LR, Adam, AdamError

N = 7
COLS = {"positions": 3, "raw_densities": 1, "raw_scales": 3, "raw_rotations": 4}


def to_dr(name, a):
    if name == "positions":
        return mi.Point3f(*[mi.Float(a[:, k]) for k in range(3)])
    if name == "raw_scales":
        return mi.Vector3f(*[mi.Float(a[:, k]) for k in range(3)])
    if name == "raw_rotations":
        return mi.Vector4f(*[mi.Float(a[:, k]) for k in range(4)])
    return mi.Float(a[:, 0])


def to_np(x):
    if dr.depth_v(x) == 1:
        return np.asarray(x, np.float64).reshape(-1, 1)
    return np.stack([np.asarray(c, np.float64) for c in x], axis=-1)


def np_adam(p, grads, lrs, b1=0.9, b2=0.999, eps=1e-15):
    """Reference: PyTorch's Adam in float64; lrs[t-1] is the lr of step t."""
    p = p.copy()
    m = np.zeros_like(p)
    v = np.zeros_like(p)
    for t, (g, lr) in enumerate(zip(grads, lrs), start=1):
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        denom = np.sqrt(v) / math.sqrt(1 - b2 ** t) + eps
        p = p - lr / (1 - b1 ** t) * m / denom
    return p, m, v


def random_problem(rng):
    params = {k: rng.normal(size=(N, c)) for k, c in COLS.items()}
    return params


@pytest.mark.parametrize("n_steps", [1, 2, 5])
def test_steps_match_numpy_reference(variant, rng, n_steps):
    params_np = random_problem(rng)
    grads_np = [{k: rng.normal(scale=10.0 ** rng.integers(-6, 1), size=(N, c))
                 for k, c in COLS.items()} for _ in range(n_steps)]
    opt = Adam(max_steps=10)   # fast decay so the schedule matters
    params = {k: to_dr(k, v.astype(np.float32)) for k, v in params_np.items()}
    for g in grads_np:
        params = opt.step(params, grads={k: to_dr(k, v.astype(np.float32)) for k, v in g.items()})
    for k in COLS:
        lrs = [DEFAULT_LR[k] * 0.1 ** (t / 10) for t in range(1, n_steps + 1)]
        ref_p, ref_m, ref_v = np_adam(params_np[k].astype(np.float32).astype(np.float64),
                                      [g[k].astype(np.float32) for g in grads_np], lrs)
        np.testing.assert_allclose(to_np(params[k]), ref_p, rtol=1e-6, atol=1e-6 * DEFAULT_LR[k])
        np.testing.assert_allclose(to_np(opt.state[k].m), ref_m, rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(to_np(opt.state[k].v), ref_v, rtol=1e-5, atol=1e-20)
        assert opt.step_count(k) == n_steps
        assert dr.grad_enabled(params[k])


def test_step_reads_dr_grad(variant, rng):
    """Gradients taken from dr.backward: loss = sum_i c_i . p_i has gradient c."""
    p_np = rng.normal(size=(N, 3)).astype(np.float32)
    c_np = rng.normal(size=(N, 3)).astype(np.float32)
    p = to_dr("positions", p_np)
    dr.enable_grad(p)
    c = to_dr("positions", c_np)
    loss = dr.sum(dr.dot(c, p))
    dr.backward(loss)
    opt = Adam()
    new = opt.step({"positions": p})
    ref, _, _ = np_adam(p_np.astype(np.float64), [c_np.astype(np.float64)],
                        [DEFAULT_LR["positions"] * 0.1 ** (1 / 30000)])
    np.testing.assert_allclose(to_np(new["positions"]), ref, rtol=1e-6, atol=1e-9)
    # the input array is left unchanged
    np.testing.assert_array_equal(to_np(p), p_np)


def test_lr_schedule_values(variant):
    opt = Adam(max_steps=1000)
    for k, lr0 in DEFAULT_LR.items():
        assert opt.lr(k, 0) == pytest.approx(lr0, rel=1e-12)
        assert opt.lr(k, 1000) == pytest.approx(0.1 * lr0, rel=1e-12)
        assert opt.lr(k, 500) == pytest.approx(lr0 * math.sqrt(0.1), rel=1e-12)
        assert opt.lr(k, 250) == pytest.approx(lr0 * 0.1 ** 0.25, rel=1e-12)
        assert opt.lr(k, 5000) == pytest.approx(0.1 * lr0, rel=1e-12)   # constant afterwards
    # annealing: past max_steps the same log rate goes on (0.1 per max_steps)
    annealing = Adam(max_steps=1000, anneal=True)
    for k, lr0 in DEFAULT_LR.items():
        for t in (0, 250, 1000):
            assert annealing.lr(k, t) == pytest.approx(opt.lr(k, t), rel=1e-12)
        assert annealing.lr(k, 1500) == pytest.approx(lr0 * 0.1 ** 1.5, rel=1e-12)
        assert annealing.lr(k, 3000) == pytest.approx(lr0 * 0.1 ** 3, rel=1e-12)
    # The first Adam step moves each coordinate by lr * g / (|g| + eps') = lr sign(g):
    # so the applied lr is observable; with iteration= it follows that position.
    p = mi.Float([0.0, 0.0])
    g = mi.Float([3.0, -2.0])
    new = opt.step({"raw_densities": p}, grads={"raw_densities": g}, iteration=500)
    np.testing.assert_allclose(np.asarray(new["raw_densities"]),
                               [-opt.lr("raw_densities", 500), opt.lr("raw_densities", 500)],
                               rtol=1e-6)


def test_zero_gradient_rows_do_not_move(variant):
    opt = Adam()
    p = mi.Float([1.0, 2.0, 3.0])
    for _ in range(3):
        p = opt.step({"raw_densities": p},
                     grads={"raw_densities": mi.Float([0.0, 1e-9, 0.0])})["raw_densities"]
    out = np.asarray(p)
    assert out[0] == 1.0 and out[2] == 3.0
    assert out[1] < 2.0   # a tiny gradient is not damped by eps = 1e-15


def _run_steps(rng, opt, n_steps=3):
    params = {k: to_dr(k, rng.normal(size=(N, c)).astype(np.float32)) for k, c in COLS.items()}
    for _ in range(n_steps):
        g = {k: to_dr(k, rng.normal(size=(N, c)).astype(np.float32)) for k, c in COLS.items()}
        params = opt.step(params, grads=g)
    return params


def test_gather_keeps_surviving_moments_exactly(variant, rng):
    opt = Adam()
    _run_steps(rng, opt)
    before = {k: (to_np(st.m), to_np(st.v), st.step) for k, st in opt.state.items()}
    idx = np.array([6, 0, 3, 3], np.uint32)     # reorder, drop, duplicate
    opt.gather(mi.UInt32(idx))
    for k, (m, v, t) in before.items():
        np.testing.assert_array_equal(to_np(opt.state[k].m), m[idx])
        np.testing.assert_array_equal(to_np(opt.state[k].v), v[idx])
        assert opt.state[k].step == t
        assert type(opt.state[k].m) is type(to_dr(k, np.zeros((1, COLS[k]), np.float32)))


def test_extend_appends_zero_moments(variant, rng):
    opt = Adam()
    _run_steps(rng, opt)
    before = {k: (to_np(st.m), to_np(st.v)) for k, st in opt.state.items()}
    opt.extend(3)
    for k, (m, v) in before.items():
        m2, v2 = to_np(opt.state[k].m), to_np(opt.state[k].v)
        assert m2.shape == (N + 3, COLS[k])
        np.testing.assert_array_equal(m2[:N], m)
        np.testing.assert_array_equal(v2[:N], v)
        assert np.all(m2[N:] == 0) and np.all(v2[N:] == 0)
    assert opt.width() == N + 3


def test_remap_mixed(variant, rng):
    opt = Adam()
    _run_steps(rng, opt)
    m_old = to_np(opt.state["raw_scales"].m)
    src = np.array([1, 2, 5, 2], np.uint32)
    keep = np.array([True, True, False, False])
    opt.remap(mi.UInt32(src), mi.Bool(keep))
    m_new = to_np(opt.state["raw_scales"].m)
    np.testing.assert_array_equal(m_new[keep], m_old[src[keep]])
    assert np.all(m_new[~keep] == 0)


def test_errors(variant, rng):
    opt = Adam()
    with pytest.raises(AdamError, match="unknown parameter group"):
        opt.step({"colour": mi.Float([1.0])}, grads={"colour": mi.Float([1.0])})
    with pytest.raises(AdamError, match="no gradient"):
        opt.step({"raw_densities": mi.Float([1.0, 2.0])})
    opt.step({"raw_densities": mi.Float([1.0, 2.0])}, grads={"raw_densities": mi.Float([1, 1])})
    with pytest.raises(AdamError, match="rows"):
        opt.step({"raw_densities": mi.Float([1.0, 2.0, 3.0])},
                 grads={"raw_densities": mi.Float([1, 1, 1])})
    with pytest.raises(AdamError, match="out of range"):
        opt.gather(mi.UInt32([0, 2]))
    with pytest.raises(AdamError, match="lr"):
        Adam(lr={"positions": float("nan")})
    checked = Adam(check_finite=True)
    with pytest.raises(AdamError, match="NaN"):
        checked.step({"raw_densities": mi.Float([1.0])},
                     grads={"raw_densities": mi.Float([float("nan")])})


def test_a_rejected_step_leaves_every_group_unchanged(variant, rng):
    """The checks (finite gradients, widths) run for every group before any update, so an
    error in the last group does not leave the first groups one step ahead."""
    opt = Adam(check_finite=True)
    params = _run_steps(rng, opt, 2)
    before = {k: (to_np(st.m), to_np(st.v), st.step) for k, st in opt.state.items()}
    g = {k: to_dr(k, rng.normal(size=(N, c)).astype(np.float32)) for k, c in COLS.items()}
    bad = np.ones((N, 4), np.float32)
    bad[2, 1] = np.inf
    with pytest.raises(AdamError, match="raw_rotations.*NaN or Inf"):
        opt.step(params, grads={**g, "raw_rotations": to_dr("raw_rotations", bad)})
    short = {**params, "raw_rotations": to_dr("raw_rotations", np.ones((N - 1, 4), np.float32))}
    with pytest.raises(AdamError, match="raw_rotations.*rows"):
        opt.step(short, grads={**g, "raw_rotations": short["raw_rotations"]})
    for k, (m, v, t) in before.items():
        assert opt.state[k].step == t, k
        np.testing.assert_array_equal(to_np(opt.state[k].m), m)
        np.testing.assert_array_equal(to_np(opt.state[k].v), v)


def test_state_dict_roundtrip(variant, rng):
    opt = Adam()
    params = _run_steps(rng, opt, 2)
    sd = opt.state_dict()
    opt2 = Adam()
    opt2.load_state_dict(sd, like=params)
    g = {k: to_dr(k, rng.normal(size=(N, c)).astype(np.float32)) for k, c in COLS.items()}
    a = opt.step(params, grads=g)
    b = opt2.step(params, grads=g)
    for k in COLS:
        np.testing.assert_array_equal(to_np(a[k]), to_np(b[k]))


def test_from_train_config(variant):
    from mi_grg.training import config
    cfg = config.TrainConfig(optim=config.Optim(lr_position=1e-3, lr_density=2e-2,
                                                lr_scale=3e-3, lr_rotation=4e-3,
                                                lr_final_ratio=0.5))
    opt = Adam.from_train_config(cfg, max_steps=100)
    assert opt.lr0 == {"positions": 1e-3, "raw_densities": 2e-2, "raw_scales": 3e-3,
                       "raw_rotations": 4e-3}
    assert opt.lr("positions", 100) == pytest.approx(5e-4)
