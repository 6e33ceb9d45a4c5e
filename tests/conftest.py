"""Shared fixtures: every test that takes ``variant`` runs on each variant present."""
import numpy as np
import pytest

import mi_grg

ALL_VARIANTS = ("llvm_ad_mono", "cuda_ad_mono")


@pytest.fixture(params=ALL_VARIANTS)
def variant(request):
    """Activate each supported variant in turn; skip those this machine lacks (no GPU)."""
    name = request.param
    if name not in mi_grg.available_variants():
        pytest.skip(f"{name} is not available on this machine")
    previous = mi_grg.variant()
    mi_grg.set_variant(name)
    yield name
    mi_grg.set_variant(previous)


@pytest.fixture
def one_thread():
    """Dr.Jit's LLVM backend on one thread: float atomics then add in one order, so two runs
    of the same seed agree (with two threads a loaded machine reorders them, and a
    borderline Gaussian can densify in one run and not in the other)."""
    import drjit as dr
    n = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(n)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def small_cone_geometry():
    """A small cone-beam scan in R2-Gaussian's normalised units (volume in [-1, 1]^3)."""
    from mi_grg.core.geometry import circular_angles
    return mi_grg.Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(24, 32),
                           sDetector=(3.0, 4.0), nVoxel=(16, 16, 16), sVoxel=(2.0, 2.0, 2.0),
                           angles=circular_angles(5))


@pytest.fixture
def crash_after():
    """crash_after(trainer, n): run ``trainer`` and let it crash (KeyboardInterrupt) at the
    start of the iteration after ``n`` iterations, as an interrupted run would (the traced
    and the recorded step both go through ``Trainer._step``)."""
    def run(trainer, n):
        step, calls = trainer._step, [0]

        def crashing_step(*a, **k):
            calls[0] += 1
            if calls[0] > n:
                raise KeyboardInterrupt
            return step(*a, **k)
        trainer._step = crashing_step
        with pytest.raises(KeyboardInterrupt):
            trainer.run()
    return run


@pytest.fixture
def kernel_hashes():
    """kernel_hashes(fn) -> (fn(), set of the hashes of the kernels fn launched), with
    Dr.Jit's kernel history on for the call (for checks that a new input size or value
    traces no new kernel, whatever the kernel cache holds)."""
    import drjit as dr

    def run(fn):
        flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history()
            out = fn()
            dr.sync_thread()
            return out, {k["hash"] for k in dr.kernel_history() if "hash" in k}
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, flag)
    return run


@pytest.fixture
def sigint_raises():
    """Ctrl-C as in a terminal (KeyboardInterrupt), whatever the test runner inherited: a
    runner started in the background (``cmd &``) inherits SIGINT ignored."""
    import signal
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture(scope="module")
def tiny_case():
    """A 16^3 Shepp-Logan case, 6 noiseless training views of 24^2 and 2 test views: the
    training loop's tests (one per module)."""
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.simulate import default_geometry, default_test_angles, simulate_case
    geo = default_geometry(n=16, det=24, views=6)
    return simulate_case("shepp", geo, default_test_angles(2), NoiseModel(), seed=3)


@pytest.fixture
def root(pristine, tmp_path):
    """A fresh copy of the module's ``pristine`` folder (CLI inputs and earlier outputs),
    for a test that may change it."""
    import shutil
    shutil.copytree(pristine, tmp_path / "w")
    return tmp_path / "w"


def _tree_hash(folder) -> dict:
    """Every path under ``folder`` (hidden ones too) -> its content's hash (None: folder)."""
    import hashlib
    return {str(p.relative_to(folder)): None if p.is_dir() else
            hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*"))}


@pytest.fixture
def tree_hash():
    """tree_hash(folder): every path under it -> its content's hash (None: folder), to show
    that a command left a folder byte for byte as it was."""
    return _tree_hash
