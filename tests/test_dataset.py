"""R2-Gaussian layout: round trips, R2's own meta_data.json format, EXR, and every bad input."""
import json

import numpy as np
import pytest

import mi_grg
from mi_grg.data.case import Case
from mi_grg.data.dataset import (NEG_TOL_REL, DatasetError, DatasetWarning, load_case, read_exr,
                            save_case, write_exr)
from mi_grg.core.geometry import circular_angles

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


# ---------------------------------------------------------------- malformed files
def _set_meta_text(text):
    return lambda root: (root / "meta_data.json").write_text(text)


def _meta_edit(fn):
    return lambda root: _edit_meta(root, fn)


def _replace_file(rel, writer):
    """Point proj_train[1] (or write ``rel``) at a file written by ``writer(path)``."""
    def mutate(root):
        writer(root / rel)
        if rel.startswith("proj_train/") and not rel.endswith("_0001.npy"):
            _edit_meta(root, lambda m: m["proj_train"][1].update(file_path=rel))
    return mutate


def _load(root):
    load_case(root)


def _write_exr_of(shape):
    return lambda root: write_exr(root / "bad.exr", np.zeros(shape, np.float32))


def _read_exr_of(make):
    def call(root):
        make(root / "x.exr")
        read_exr(root / "x.exr")
    return call


def _two_channel_exr(path):
    import OpenEXR
    img = np.zeros((NV, NU), np.float32)
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"R": img, "G": img}).write(str(path))


# (id, mutate the R2 case, action on the case directory, message pattern naming the
# file or field)
BAD_INPUTS = [
    ("invalid-json", _set_meta_text('{"scanner": {'), _load,
     r"meta_data.json: not valid JSON"),
    ("json-not-an-object", _set_meta_text("[1, 2]"), _load,
     r"meta_data.json: lacks the 'scanner' object"),
    ("no-scanner", _meta_edit(lambda m: m.pop("scanner")), _load,
     r"meta_data.json: lacks the 'scanner' object"),
    ("scanner-not-an-object", _meta_edit(lambda m: m.update(scanner=[7.0, 5.0])), _load,
     r"meta_data.json: lacks the 'scanner' object"),
    ("scanner-field-missing", _meta_edit(lambda m: m["scanner"].pop("nDetector")), _load,
     r"meta_data.json: scanner: .*nDetector"),
    ("proj-train-not-a-list", _meta_edit(lambda m: m.update(proj_train={"0": "a.npy"})), _load,
     r"meta_data.json: 'proj_train' must be a list, got dict"),
    ("proj-test-not-a-list", _meta_edit(lambda m: m.update(proj_test="proj_test")), _load,
     r"meta_data.json: 'proj_test' must be a list, got str"),
    ("entry-without-file-path", _meta_edit(lambda m: m["proj_train"][1].pop("file_path")),
     _load, r"proj_train\[1\] lacks 'file_path'"),
    ("entry-without-angle", _meta_edit(lambda m: m["proj_test"][0].pop("angle")), _load,
     r"proj_test\[0\] lacks 'angle'"),
    ("entry-not-an-object", _meta_edit(lambda m: m["proj_train"].__setitem__(0, "a.npy")),
     _load, r"proj_train\[0\] must be an object with file_path and angle"),
    ("file-path-empty", _meta_edit(lambda m: m["proj_train"][0].update(file_path="")), _load,
     r"proj_train\[0\]\.file_path must be a non-empty path"),
    ("file-path-not-a-string", _meta_edit(lambda m: m["proj_train"][0].update(file_path=3)),
     _load, r"proj_train\[0\]\.file_path must be a non-empty path"),
    ("unknown-suffix", _replace_file("proj_train/p.png", lambda p: p.write_bytes(b"\x89PNG")),
     _load, r"proj_train\[1\]: .*p\.png must be \.npy or \.exr"),
    ("corrupt-npy", _replace_file("proj_train/proj_train_0001.npy",
                                  lambda p: p.write_bytes(b"not an npy file")),
     _load, r"proj_train\[1\]: cannot read .*proj_train_0001\.npy as \.npy"),
    ("pickled-npy", _replace_file("proj_train/proj_train_0001.npy",
                                  lambda p: np.save(p, np.full((NV, NU), None, object))),
     _load, r"proj_train\[1\]: cannot read .*proj_train_0001\.npy as \.npy"),
    ("string-dtype", _replace_file("proj_train/proj_train_0001.npy",
                                   lambda p: np.save(p, np.full((NV, NU), "0.5"))),
     _load, r"proj_train\[1\]: .*proj_train_0001\.npy must hold real numbers, got dtype <U3"),
    ("complex-dtype", _replace_file("proj_train/proj_train_0001.npy",
                                    lambda p: np.save(p, np.ones((NV, NU), np.complex64))),
     _load, r"proj_train\[1\]: .*must hold real numbers, got dtype complex64"),
    ("bool-dtype", _replace_file("proj_train/proj_train_0001.npy",
                                 lambda p: np.save(p, np.ones((NV, NU), bool))),
     _load, r"proj_train\[1\]: .*must hold real numbers, got dtype bool"),
    ("corrupt-exr", _replace_file("proj_train/p.exr", lambda p: p.write_bytes(b"v/1\x01junk")),
     _load, r"p\.exr: cannot read as OpenEXR"),
    ("corrupt-vol", _replace_file("vol_gt.npy", lambda p: p.write_bytes(b"\x93NUMPY junk")),
     _load, r"vol: cannot read .*vol_gt\.npy as \.npy"),
    ("our-block-not-an-object", _meta_edit(lambda m: m.update(mi_grg=[1])), _load,
     r"meta_data.json: 'mi_grg' must be an object"),
    ("write-exr-3d", None, _write_exr_of((2, NV, NU)),
     r"bad\.exr: an EXR image must be 2-D \[v, u\], got shape \(2, 6, 8\)"),
    ("write-exr-1d", None, _write_exr_of((NU,)),
     r"bad\.exr: an EXR image must be 2-D \[v, u\], got shape \(8,\)"),
    ("write-exr-empty", None, _write_exr_of((0, NU)),
     r"bad\.exr: an EXR image must be 2-D \[v, u\], got shape \(0, 8\)"),
    ("read-exr-missing", None, lambda root: read_exr(root / "none.exr"),
     r"none\.exr: EXR file not found"),
    ("read-exr-two-channels", None, _read_exr_of(_two_channel_exr),
     r"x\.exr: expected one channel 'Y', found \['G', 'R'\]"),
]


@pytest.mark.parametrize("mutate, action, pattern", [b[1:] for b in BAD_INPUTS],
                         ids=[b[0] for b in BAD_INPUTS])
def test_bad_input_names_the_file_or_field(tmp_path, rng, mutate, action, pattern):
    _write_r2_case(tmp_path, rng)
    load_case(tmp_path)                  # the untouched case loads: the mutation is the fault
    if mutate is not None:
        mutate(tmp_path)
    with pytest.raises(DatasetError, match=pattern):
        action(tmp_path)


# ---------------------------------------------------------------- echoed into metrics.json
def test_clamp_is_recorded_per_split_and_echoed_into_metrics(tmp_path, rng):
    from mi_grg.methods import reconstruct, register_method
    projs = _stack_with_negative(rng, -0.5 * NEG_TOL_REL)
    projs["proj_test"][0][1, 1] = -1e-4 * projs["proj_test"][0].max()
    _write_r2_case(tmp_path, rng, projs=projs)
    with pytest.warns(DatasetWarning):
        got = load_case(tmp_path)
    peak = max(p.max() for p in projs["proj_train"])
    assert set(got.clamped) == {"proj_train", "proj_test"}
    train = got.clamped["proj_train"]
    assert train["count"] == 2
    assert train["min"] == pytest.approx(float(np.float32(-0.5 * NEG_TOL_REL * peak)))
    assert train["tolerance"] == pytest.approx(NEG_TOL_REL * peak)
    assert got.clamped["proj_test"]["count"] == 1
    register_method("zeros", lambda c: np.zeros(c.geometry.nVoxel, np.float32))
    _, metrics = reconstruct(got, "zeros", tmp_path / "out")
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["clamped_negatives"] == saved["clamped_negatives"] == got.clamped
    # the repair is not written back as data: a re-saved case carries no clamp record
    save_case(got, tmp_path / "again")
    assert load_case(tmp_path / "again").clamped == {}


def test_unclamped_case_records_nothing(tmp_path, rng):
    _write_r2_case(tmp_path, rng)
    assert load_case(tmp_path).clamped == {}


def test_metrics_echo_the_geometry_in_file_units(tmp_path, rng):
    from mi_grg.methods import reconstruct, register_method
    case = _case(rng)                   # lengths in mm: load_case rescales by 2 / 320
    save_case(case, tmp_path)
    got = load_case(tmp_path)
    assert got.scene_scale != 1.0
    register_method("zeros", lambda c: np.zeros(c.geometry.nVoxel, np.float32))
    reconstruct(got, "zeros", tmp_path / "out")
    geo = json.loads((tmp_path / "out" / "metrics.json").read_text())["geometry"]
    f = case.geometry
    assert geo["mode"] == f.mode and geo["nDetector"] == list(f.nDetector)
    assert geo["nVoxel"] == list(f.nVoxel)
    for k in ("DSD", "DSO", "sDetector", "sVoxel", "offOrigin", "offDetector"):
        np.testing.assert_allclose(geo[k], getattr(f, k), rtol=1e-12, err_msg=k)
    assert geo["n_angles"] == 3 and geo["n_test_angles"] == 2
    assert geo["scene_scale"] == pytest.approx(2.0 / 320.0)
