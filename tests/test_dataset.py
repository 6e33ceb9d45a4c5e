"""R2-Gaussian layout: round trips, R2's own meta_data.json format, EXR, and every bad input."""
import json

import numpy as np
import pytest

import mi_grg
from mi_grg.case import Case
from mi_grg.dataset import (NEG_TOL_REL, DatasetError, DatasetWarning, load_case, read_exr,
                            save_case, write_exr)
from mi_grg.geometry import circular_angles

NV, NU = 6, 8          # detector [v, u]
NVOX = (4, 5, 7)       # volume [x, y, z]


def _case(rng, scene_scale=1.0, info=None):
    geo = mi_grg.Geometry(mode="cone", DSD=1500.0, DSO=1000.0, nDetector=(NV, NU),
                          sDetector=(300.0, 410.0), nVoxel=NVOX, sVoxel=(200.0, 250.0, 320.0),
                          offOrigin=(1.0, -2.0, 3.0), offDetector=(0.5, -1.5),
                          angles=circular_angles(3, start_angle=0.25))
    return Case(geometry=geo, train=rng.random((3, NV, NU)).astype(np.float32),
                test_angles=np.array([0.1, 2.5]),
                test=rng.random((2, NV, NU)).astype(np.float32),
                vol_gt=rng.random(NVOX).astype(np.float32), scene_scale=scene_scale,
                info={"phantom": "blobs", "noise": {"I0": 1e4, "sigma": 0.0}, "seed": 7}
                if info is None else info)


def _geo_fields(g):
    return {k: getattr(g, k) for k in ("mode", "DSD", "DSO", "nDetector", "sDetector",
                                       "nVoxel", "sVoxel", "offOrigin", "offDetector")}


def _assert_geo_equal(a, b, rel=1e-12):
    fa, fb = _geo_fields(a), _geo_fields(b)
    assert fa["mode"] == fb["mode"]
    for k in fa:
        if k != "mode":
            np.testing.assert_allclose(fa[k], fb[k], rtol=rel, atol=1e-12, err_msg=k)
    np.testing.assert_allclose(a.angles, b.angles, rtol=0, atol=0)


# ---------------------------------------------------------------- round trips
def test_round_trip_without_rescale(tmp_path, rng):
    case = _case(rng)
    save_case(case, tmp_path)
    got = load_case(tmp_path, rescale=False)
    assert got.scene_scale == 1.0
    _assert_geo_equal(got.geometry, case.geometry)
    np.testing.assert_array_equal(got.train, case.train)
    np.testing.assert_array_equal(got.test, case.test)
    np.testing.assert_array_equal(got.test_angles, case.test_angles)
    np.testing.assert_array_equal(got.vol_gt, case.vol_gt)
    assert got.train.dtype == got.test.dtype == got.vol_gt.dtype == np.float32
    assert got.info == case.info


def test_rescale_multiplies_lengths_and_projections(tmp_path, rng):
    case = _case(rng)
    save_case(case, tmp_path)
    got = load_case(tmp_path)                       # rescale=True is the default
    s = 2.0 / 320.0                                 # 2 / max(sVoxel)
    assert got.scene_scale == pytest.approx(s, rel=1e-15)
    g, f = got.geometry, case.geometry
    for name in ("DSD", "DSO"):
        assert getattr(g, name) == pytest.approx(getattr(f, name) * s, rel=1e-12)
    for name in ("sDetector", "sVoxel", "offOrigin", "offDetector"):
        np.testing.assert_allclose(getattr(g, name), np.multiply(getattr(f, name), s),
                                   rtol=1e-12, err_msg=name)
    np.testing.assert_allclose(g.dDetector, np.multiply(f.dDetector, s), rtol=1e-12)
    np.testing.assert_allclose(g.dVoxel, np.multiply(f.dVoxel, s), rtol=1e-12)
    assert max(g.sVoxel) == pytest.approx(2.0, rel=1e-14)
    assert g.nDetector == f.nDetector and g.nVoxel == f.nVoxel
    np.testing.assert_allclose(got.train, case.train.astype(np.float64) * s, rtol=1e-6)
    np.testing.assert_allclose(got.test, case.test.astype(np.float64) * s, rtol=1e-6)
    np.testing.assert_array_equal(got.vol_gt, case.vol_gt)      # densities untouched
    np.testing.assert_array_equal(got.geometry.angles, case.geometry.angles)


def test_save_undoes_rescale(tmp_path, rng):
    """load(rescale) -> save -> load(no rescale) gives back the files' units."""
    case = _case(rng)
    save_case(case, tmp_path / "a")
    scaled = load_case(tmp_path / "a")
    save_case(scaled, tmp_path / "b")
    back = load_case(tmp_path / "b", rescale=False)
    _assert_geo_equal(back.geometry, case.geometry, rel=1e-12)
    np.testing.assert_allclose(back.train, case.train, rtol=1e-6)
    np.testing.assert_allclose(back.test, case.test, rtol=1e-6)
    meta = json.loads((tmp_path / "b" / "meta_data.json").read_text())
    assert meta["scanner"]["sVoxel"] == pytest.approx([200.0, 250.0, 320.0], rel=1e-12)
    np.testing.assert_allclose(meta["bbox"], case.geometry.bbox(), rtol=1e-12)


def test_case_without_test_views_or_volume(tmp_path, rng):
    case = _case(rng)
    case = Case(geometry=case.geometry, train=case.train)
    save_case(case, tmp_path)
    meta = json.loads((tmp_path / "meta_data.json").read_text())
    assert meta["proj_test"] == [] and "vol" not in meta
    got = load_case(tmp_path, rescale=False)
    assert got.test is None and got.test_angles.size == 0 and got.vol_gt is None


def test_exr_round_trip_bit_exact(tmp_path, rng):
    img = (rng.standard_normal((NV, NU)) * 1e3).astype(np.float32)
    img[0, 0] = np.float32(1e-40)            # a subnormal survives too
    img[1, 2] = np.nextafter(np.float32(1), np.float32(2))
    write_exr(tmp_path / "p.exr", img)
    back = read_exr(tmp_path / "p.exr")
    assert back.dtype == np.float32 and back.shape == (NV, NU)
    assert np.array_equal(back.view(np.uint32), img.view(np.uint32))


def test_save_with_exr_and_load_exr_paths(tmp_path, rng):
    case = _case(rng)
    save_case(case, tmp_path, exr=True)
    meta = json.loads((tmp_path / "meta_data.json").read_text())
    for e in meta["proj_train"] + meta["proj_test"]:
        npy = np.load(tmp_path / e["file_path"])
        exr = read_exr((tmp_path / e["file_path"]).with_suffix(".exr"))
        assert np.array_equal(npy, exr)
        e["file_path"] = e["file_path"][:-4] + ".exr"       # point the layout at the EXRs
        (tmp_path / e["file_path"]).with_suffix(".npy").unlink()
    (tmp_path / "meta_data.json").write_text(json.dumps(meta))
    got = load_case(tmp_path, rescale=False)
    np.testing.assert_array_equal(got.train, case.train)
    np.testing.assert_array_equal(got.test, case.test)


# ---------------------------------------------------------------- R2's own format
def _write_r2_case(root, rng, n_train=2, n_test=1, proj_shape=(NV, NU), vol_shape=NVOX,
                   projs=None):
    """A case exactly as R2-Gaussian's generate_data.py writes it (scanner = its yml)."""
    scanner = {
        "mode": "cone", "filter": None, "DSD": 7.0, "DSO": 5.0,
        "nDetector": [NV, NU], "sDetector": [3.0, 4.0],
        "nVoxel": list(NVOX), "sVoxel": [2.0, 2.0, 2.0],
        "offOrigin": [0, 0, 0], "offDetector": [0, 0],
        "accuracy": 0.5, "totalAngle": 360.0, "startAngle": 0.0,
        "noise": True, "possion_noise": 10000, "gaussian_noise": [0, 10],
    }
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "vol_gt.npy", rng.random(vol_shape).astype(np.float32))
    meta = {"scanner": scanner, "vol": "vol_gt.npy", "bbox": [[-1, -1, -1], [1, 1, 1]]}
    arrays = {}
    for split, n in (("proj_train", n_train), ("proj_test", n_test)):
        (root / split).mkdir(exist_ok=True)
        meta[split] = []
        for i in range(n):
            rel = f"{split}/{split}_{i:04d}.npy"
            arr = (rng.random(proj_shape).astype(np.float32) if projs is None
                   else projs[split][i])
            np.save(root / rel, arr)
            arrays.setdefault(split, []).append(arr)
            meta[split].append({"file_path": rel, "angle": float(np.float64(i * 0.7 + 0.1))})
    with open(root / "meta_data.json", "w", encoding="utf-8") as f:
        json.dump(meta, f, indent=4)
    return meta, arrays


def test_loads_r2_generated_layout(tmp_path, rng):
    meta, arrays = _write_r2_case(tmp_path, rng)
    got = load_case(tmp_path)
    assert got.scene_scale == pytest.approx(1.0)          # sVoxel = 2 already
    g = got.geometry
    assert (g.mode, g.DSD, g.DSO, g.nDetector, g.nVoxel) == ("cone", 7.0, 5.0, (NV, NU), NVOX)
    np.testing.assert_array_equal(g.angles, [e["angle"] for e in meta["proj_train"]])
    np.testing.assert_array_equal(got.test_angles, [e["angle"] for e in meta["proj_test"]])
    np.testing.assert_array_equal(got.train, np.stack(arrays["proj_train"]))
    assert got.info["scanner_extras"]["accuracy"] == 0.5
    assert got.info["scanner_extras"]["filter"] is None
    # Saving writes R2's TIGRE extras back; its get_geometry needs accuracy and filter.
    save_case(got, tmp_path / "again")
    sc = json.loads((tmp_path / "again" / "meta_data.json").read_text())["scanner"]
    for k, v in meta["scanner"].items():
        assert sc[k] == pytest.approx(v) if isinstance(v, (int, float)) else sc[k] == v, k


def test_meta_json_path_is_accepted(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    assert load_case(tmp_path / "meta_data.json").train.shape == (2, NV, NU)


def test_r2_scanner_with_non_unit_volume_rescales(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    meta = json.loads((tmp_path / "meta_data.json").read_text())
    sc = meta["scanner"]
    sc.update(DSD=700.0, DSO=500.0, sDetector=[300.0, 400.0], sVoxel=[100.0, 200.0, 150.0],
              offOrigin=[10.0, 0.0, -5.0], dVoxel=[25.0, 40.0, 150.0 / 7])
    (tmp_path / "meta_data.json").write_text(json.dumps(meta))
    raw = np.load(tmp_path / "proj_train" / "proj_train_0001.npy")
    got = load_case(tmp_path)
    s = 2.0 / 200.0
    assert got.scene_scale == pytest.approx(s)
    assert got.geometry.DSO == pytest.approx(5.0) and got.geometry.DSD == pytest.approx(7.0)
    np.testing.assert_allclose(got.geometry.offOrigin, [0.1, 0.0, -0.05], rtol=1e-12)
    np.testing.assert_allclose(got.train[1], raw * s, rtol=1e-6)


# ---------------------------------------------------------------- bad inputs
def _edit_meta(root, fn):
    p = root / "meta_data.json"
    meta = json.loads(p.read_text())
    fn(meta)
    p.write_text(json.dumps(meta))


def test_missing_meta(tmp_path):
    with pytest.raises(DatasetError, match="meta_data.json not found"):
        load_case(tmp_path)


def test_missing_projection_file(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    (tmp_path / "proj_train" / "proj_train_0001.npy").unlink()
    with pytest.raises(DatasetError, match=r"proj_train\[1\].*proj_train_0001.npy not found"):
        load_case(tmp_path)


def test_wrong_projection_shape(tmp_path, rng):
    _write_r2_case(tmp_path, rng, proj_shape=(NU, NV))
    with pytest.raises(DatasetError, match=r"expected \[v, u\] = \[6, 8\]"):
        load_case(tmp_path)


def test_wrong_volume_shape(tmp_path, rng):
    _write_r2_case(tmp_path, rng, vol_shape=(7, 5, 4))
    with pytest.raises(DatasetError, match=r"vol.*expected \[x, y, z\] = \[4, 5, 7\]"):
        load_case(tmp_path)


def test_missing_volume_file_gives_none(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    (tmp_path / "vol_gt.npy").unlink()
    with pytest.warns(DatasetWarning, match="vol file"):
        assert load_case(tmp_path).vol_gt is None


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_projection(tmp_path, rng, bad):
    _write_r2_case(tmp_path, rng)
    p = tmp_path / "proj_test" / "proj_test_0000.npy"
    arr = np.load(p)
    arr[2, 3] = bad
    np.save(p, arr)
    with pytest.raises(DatasetError, match=r"proj_test.*NaN/Inf.*\[0, 2, 3\]"):
        load_case(tmp_path)


def test_non_finite_volume(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    vol = np.load(tmp_path / "vol_gt.npy")
    vol[1, 1, 1] = np.nan
    np.save(tmp_path / "vol_gt.npy", vol)
    with pytest.raises(DatasetError, match="vol.*NaN/Inf"):
        load_case(tmp_path)


def _stack_with_negative(rng, value):
    projs = {"proj_train": [rng.random((NV, NU)).astype(np.float32) + 0.5 for _ in range(2)],
             "proj_test": [rng.random((NV, NU)).astype(np.float32) + 0.5]}
    peak = max(p.max() for p in projs["proj_train"])
    projs["proj_train"][1][4, 5] = value * peak
    projs["proj_train"][0][0, 0] = value * peak
    return projs


def test_small_negatives_clamped_with_warning(tmp_path, rng):
    projs = _stack_with_negative(rng, -0.5 * NEG_TOL_REL)
    _write_r2_case(tmp_path, rng, projs=projs)
    with pytest.warns(DatasetWarning, match="clamped 2 negative"):
        got = load_case(tmp_path, rescale=False)
    assert got.train[1, 4, 5] == 0.0 and got.train[0, 0, 0] == 0.0
    assert got.train.min() == 0.0
    np.testing.assert_array_equal(got.train[1, 0], projs["proj_train"][1][0])


def test_large_negative_raises(tmp_path, rng):
    projs = _stack_with_negative(rng, -2 * NEG_TOL_REL)
    _write_r2_case(tmp_path, rng, projs=projs)
    with pytest.raises(DatasetError, match="proj_train.*below"):
        load_case(tmp_path)


def test_empty_proj_train(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    _edit_meta(tmp_path, lambda m: m.update(proj_train=[]))
    with pytest.raises(DatasetError, match="proj_train.*empty"):
        load_case(tmp_path)


@pytest.mark.parametrize("angle", ["0.5", None, True, [0.1]])
def test_angle_not_a_number(tmp_path, rng, angle):
    _write_r2_case(tmp_path, rng)
    _edit_meta(tmp_path, lambda m: m["proj_test"][0].update(angle=angle))
    with pytest.raises(DatasetError, match=r"proj_test\[0\]\.angle must be a finite number"):
        load_case(tmp_path)


def test_bad_scanner_field_is_named(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    _edit_meta(tmp_path, lambda m: m["scanner"].update(DSO=9.0))   # DSO >= DSD in cone mode
    with pytest.raises(DatasetError, match="meta_data.json.*DSO"):
        load_case(tmp_path)


def test_save_validates_case(tmp_path, rng):
    case = _case(rng)
    with pytest.raises(DatasetError, match=r"case.train.*\[view, v, u\] = \[3, 6, 8\]"):
        save_case(Case(geometry=case.geometry, train=case.train[:, :, :-1]), tmp_path)
    bad = case.train.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(DatasetError, match="case.train contains NaN"):
        save_case(Case(geometry=case.geometry, train=bad), tmp_path)
    with pytest.raises(DatasetError, match="JSON"):
        save_case(Case(geometry=case.geometry, train=case.train, info={"x": object()}),
                  tmp_path)
    assert not (tmp_path / "meta_data.json").exists()
