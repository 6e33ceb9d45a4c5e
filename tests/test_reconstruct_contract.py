"""The reconstruction contract: files, shapes, units and metrics of every method's output."""
import json

import numpy as np
import pytest

from mi_grg.data.case import Case
from mi_grg import __version__
from mi_grg.methods import code_version, get_method, reconstruct, register_method


def _case(small_cone_geometry, rng):
    geo = small_cone_geometry
    gt = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    train = rng.uniform(0, 1, geo.projection_shape).astype(np.float32)
    return Case(geometry=geo, train=train, vol_gt=gt, info={"phantom": "random"})


def test_outputs_follow_the_contract(tmp_path, small_cone_geometry, rng):
    case = _case(small_cone_geometry, rng)
    noise = rng.normal(0, 0.1, case.vol_gt.shape).astype(np.float32)
    register_method("gt-plus-noise", lambda c, scale=1.0: c.vol_gt + scale * noise)
    vol, metrics = reconstruct(case, "gt-plus-noise", tmp_path, scale=0.5)
    pred = np.load(tmp_path / "vol_pred.npy")
    assert pred.shape == case.vol_gt.shape and pred.dtype == np.float32
    np.testing.assert_array_equal(pred, vol)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    mse = np.mean((0.5 * noise.astype(np.float64)) ** 2)
    assert saved["psnr_3d"] == pytest.approx(10 * np.log10(1 / mse), rel=1e-5)
    assert 0 < saved["ssim_3d"] < 1
    assert saved["method"] == "gt-plus-noise" and saved["options"] == {"scale": 0.5}
    assert saved["data"] == {"phantom": "random"} and saved["seconds"] >= 0
    assert "variant" in saved["machine"]
    assert saved["machine"]["mi_grg"] == code_version()
    assert (tmp_path / "slices.png").stat().st_size > 1000


def test_code_version_names_the_checkout_commit():
    """Which code produced a result: the version is the package's, and in a checkout its
    "+g<hash>" resolves to the checkout's HEAD (what "+dirty" means is checked on a scratch
    repository below)."""
    import re
    import shutil
    import subprocess
    from pathlib import Path
    import mi_grg
    v = code_version()
    root = Path(mi_grg.__file__).resolve().parents[1]
    if shutil.which("git") is None or not (root / ".git").exists():
        assert v == __version__   # installed outside a checkout
        return
    m = re.fullmatch(re.escape(__version__) + r"\+g([0-9a-f]{4,40})(\+dirty)?", v)
    assert m, v

    def rev(name):
        return subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", name],
                              capture_output=True, text=True, check=True).stdout.strip()
    assert rev(m.group(1) + "^{commit}") == rev("HEAD")


def test_code_version_dirty_only_for_code(tmp_path):
    """A benchmark rewriting its result files (docs/) leaves the version clean; an edit under
    mi_grg/ marks it "+dirty" (a scratch git repository)."""
    import shutil
    import subprocess
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    (tmp_path / "mi_grg").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "mi_grg" / "a.py").write_text("x = 1\n")
    (tmp_path / "docs" / "r.md").write_text("old\n")
    for cmd in (["init", "-q"], ["add", "-A"], ["commit", "-qm", "c"]):
        subprocess.run(git + cmd, check=True, capture_output=True)
    head = subprocess.run(git + ["rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    assert code_version(tmp_path) == f"{__version__}+g{head}"
    (tmp_path / "docs" / "r.md").write_text("new result\n")
    assert code_version(tmp_path) == f"{__version__}+g{head}"
    (tmp_path / "mi_grg" / "a.py").write_text("x = 2\n")
    assert code_version(tmp_path) == f"{__version__}+g{head}+dirty"


def test_code_version_without_git(monkeypatch):
    import subprocess

    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")
    monkeypatch.setattr(subprocess, "run", no_git)
    assert code_version() == __version__


def test_wrong_shape_and_nan_are_caught(small_cone_geometry, rng):
    case = _case(small_cone_geometry, rng)
    register_method("bad-shape", lambda c: np.zeros((3, 3, 3)))
    with pytest.raises(RuntimeError, match="nVoxel"):
        reconstruct(case, "bad-shape")
    register_method("nan", lambda c: np.full(c.geometry.nVoxel, np.nan))
    with pytest.raises(RuntimeError, match="NaN"):
        reconstruct(case, "nan")


def test_unknown_method_lists_the_valid_ones():
    with pytest.raises(ValueError, match="fdk"):
        get_method("fbk")
