"""The Mitsuba-rendered 3-D preview (mi_grg.evaluation.preview): the transfer function's
breakpoints from a histogram worked out by hand, the emission-absorption integral against
its closed form, the screen orientation of +y and +z, the written files, bad input."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

import mi_grg  # noqa: F401  (sets the variant)
from mi_grg.evaluation import preview as pv


def test_transfer_function_breakpoints_from_quantiles():
    vol = np.zeros((20, 20, 20), np.float32)
    flat = vol.reshape(-1)
    flat[:1000] = 0.5          # the bulk
    flat[1000:1010] = 2.0      # 10 dense voxels: above the 99.5th percentile rank of 1010
    flat[1010:1020] = 0.01     # faint noise: below hi / 10, not part of the bulk
    flat[1020:1030] = -0.3     # negatives are ignored
    tf = pv.transfer_function(vol)
    assert tf["hi"] == pytest.approx(2.0)
    assert tf["lo"] == tf["start"] == pytest.approx(0.5)
    assert tf["lut"].shape == (pv.LUT_SIZE, 4)
    np.testing.assert_allclose(tf["lut"][[0, -1], 3], [0.0, 1.0])   # opacity ramp


def test_uniform_volume_ramps_from_zero():
    tf = pv.transfer_function(np.full((4, 4, 4), 3.0, np.float32))
    assert tf["start"] == 0.0 and tf["hi"] == pytest.approx(3.0)


@pytest.mark.parametrize("vol, message", [
    (np.zeros((8, 8, 8)), "all zero"),
    (np.full((8, 8, 8), -1.0), "never positive"),
    (np.where(np.eye(8)[:, :, None] > 0, np.nan, 1.0) * np.ones((8, 8, 8)), "non-finite"),
])
def test_empty_or_non_finite_volume_is_refused(vol, message):
    with pytest.raises(ValueError, match=message):
        pv.transfer_function(vol)


def _uniform_tf(start=0.0, hi=1.0):
    """Grey colour 1, opacity fraction = x: the closed form needs nothing else."""
    x = np.linspace(0.0, 1.0, pv.LUT_SIZE)
    lut = np.stack([np.ones_like(x), np.ones_like(x), np.ones_like(x), x], 1)
    return {"start": start, "hi": hi, "lut": lut.astype(np.float32)}


def test_emission_absorption_matches_closed_form():
    """A uniform cube at density 0.25 of the ramp: the central ray of every view crosses
    it over 1 / cos(elevation) (the box's longest side is 1), so
    alpha = 1 - exp(-OPTICAL_DEPTH * 0.25 * L), colour = alpha (premultiplied grey)."""
    vol = np.full((8, 8, 8), 0.25, np.float32)
    elev = 20.0
    rgba = pv.render_views(vol, n_views=2, size=33, spp=16, elevation_deg=elev,
                           tf=_uniform_tf(), framing=(np.zeros(3), 0.9))
    path = 1.0 / np.cos(np.radians(elev))
    alpha = 1.0 - np.exp(-pv.OPTICAL_DEPTH * 0.25 * path)
    centre = rgba[:, 16, 16, :]
    np.testing.assert_allclose(centre[:, 3], alpha, atol=5e-3)
    np.testing.assert_allclose(centre[:, 0], alpha, atol=5e-3)
    assert np.all(rgba[:, 0, 0, 3] == 0.0)        # a corner ray misses the box


def _blob(index):
    vol = np.zeros((16, 16, 16), np.float32)
    i, j, k = index
    vol[i:i + 3, j:j + 3, k:k + 3] = 1.0
    return vol


def _centroid(alpha):
    rows, cols = np.nonzero(alpha > 0.05)
    return rows.mean() / alpha.shape[0], cols.mean() / alpha.shape[1]


@pytest.mark.parametrize("index, view, where", [
    ((6, 12, 6), 0, "right"),     # +y seen from +x with +z up: on the right
    ((12, 6, 6), 1, "left"),      # +x seen from +y: on the left
    ((6, 6, 12), 0, "top"),       # +z: up on the screen
    ((6, 1, 6), 0, "left"),       # -y seen from +x: on the left
])
def test_screen_orientation(index, view, where):
    rgba = pv.render_views(_blob(index), n_views=4, size=48, spp=1, elevation_deg=0.0,
                           framing=(np.zeros(3), 0.9))
    row, col = _centroid(rgba[view, :, :, 3])
    expect = {"right": col > 0.6, "left": col < 0.4, "top": row < 0.4}[where]
    assert expect, (row, col)


def _run(tmp_path, vol, geometry=None, units=None):
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "vol_pred.npy", vol.astype(np.float32))
    geometry = geometry or {"nVoxel": list(vol.shape), "sVoxel": [2.0] * 3}
    (run / "metrics.json").write_text(json.dumps(
        {"method": "gr", "geometry": geometry, "data": {"units": units} if units else {}}))
    return run


def test_write_preview_files(tmp_path):
    from PIL import Image
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.core.geometry import Geometry, circular_angles
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(8, 8), sDetector=(3.0, 3.0),
                   nVoxel=(24, 24, 24), sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(2))
    run = _run(tmp_path, make_phantom("shepp").voxelize(geo),
               units={"length": "mm", "density": "1/mm", "normalised": False})
    res = pv.write_preview(run, n_views=6, size=64, spp=1)
    assert res["png"] == run / "preview.png" and res["unit"] == "mm"
    png = np.asarray(Image.open(res["png"]).convert("RGB"))
    assert png.shape[0] > 100 and png.max() > 200          # something bright drawn
    gif = Image.open(res["gif"])
    assert gif.n_frames == 6 and gif.size == (64, 64)
    frame = np.asarray(gif.convert("RGB"))
    assert frame.max() > 240 and frame[0, 0].max() == 0   # exposed to ~white, black corner


def test_cli_preview_errors_are_one_line(tmp_path, capsys):
    from mi_grg.cli import main
    rc = main(["render", "--run", str(tmp_path), "--preview"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "vol_pred.npy not found" in err
    run = _run(tmp_path, np.zeros((8, 8, 8)))
    rc = main(["render", "--run", str(run), "--preview"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "all zero: nothing to preview" in err
    assert not (run / "preview.png").exists()


@pytest.mark.slow
def test_preview_64_cubed_under_a_minute(tmp_path):
    """The issue's target, on the CI CPU: a 64^3 FDK-like noisy volume, default settings."""
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.core.geometry import Geometry, circular_angles
    geo = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(8, 8), sDetector=(3.0, 3.0),
                   nVoxel=(64, 64, 64), sVoxel=(2.0, 2.0, 2.0), angles=circular_angles(2))
    vol = make_phantom("shepp").voxelize(geo)
    vol = vol + np.random.default_rng(0).normal(0, 0.05, vol.shape)
    run = _run(tmp_path, vol)
    t0 = time.perf_counter()
    pv.write_preview(run)
    assert time.perf_counter() - t0 < 60.0
