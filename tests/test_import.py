"""mi-grg import: a synthetic raw scan (made here from exact line integrals of an analytic
phantom) goes through TIFF reading, flat/dark or free-ray normalisation, centre-of-rotation
estimation, view selection and the reference volume; bad input fails with one line, exit 2,
and no output directory. Also: PSNR data range in physical units, and unit-independence of
the methods (mi_grg.data.units)."""
from __future__ import annotations

import json
import os
import pickle

import numpy as np
import pytest
import tifffile

from mi_grg.core.fdk import fdk
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.dataset import load_case
from mi_grg.data.phantoms import make_phantom
from mi_grg.data.cor import estimate_cor
from mi_grg.data.dataset import DatasetError
from mi_grg.data.naf import load_naf
from mi_grg.data.raw_import import import_scan, normalise
from mi_grg.evaluation.metrics import psnr_3d

NV = NU = 48
N_VIEWS = 60
PX = 0.4                 # mm
DSD, DSO = 500.0, 300.0  # mm
SHIFT_PX = 3.4           # true offDetector[1] in pixels
SIDE = 8.0               # mm, the phantom's box
I0 = 2.0e4
K = 0.25                 # phantom density scale: 1/mm, line integrals up to ~2


def true_geometry(n_vox=24, shift=SHIFT_PX):
    return Geometry(mode="cone", DSD=DSD, DSO=DSO, nDetector=(NV, NU),
                    sDetector=(NV * PX, NU * PX), nVoxel=(n_vox,) * 3, sVoxel=(SIDE,) * 3,
                    offDetector=(0.0, shift * PX), angles=circular_angles(N_VIEWS))


@pytest.fixture(scope="module")
def scan():
    """Exact line integrals, a non-uniform flat, darks, a drifting source -> counts."""
    rng = np.random.default_rng(7)
    geo = true_geometry()
    p = K * make_phantom("shepp").line_integrals(geo)
    v, u = np.meshgrid(np.arange(NV), np.arange(NU), indexing="ij")
    flat_v = 1.0 + 0.15 * np.cos(np.pi * v / NV)                    # vertical shading
    flat = flat_v * (1.0 + 0.08 * np.sin(2 * np.pi * u / NU + 0.3))  # and horizontal
    dark = 100.0 + 20.0 * rng.random((NV, NU))
    drift = 1.0 + 0.05 * np.sin(np.arange(N_VIEWS) * 0.21)

    def counts(mean):
        return np.clip(np.round(rng.poisson(mean) + dark + rng.normal(0, 3, mean.shape)),
                       0, 65535).astype(np.uint16)

    expect = I0 * drift[:, None, None] * np.exp(-p)
    return {"geo": geo, "p": p, "flat": flat, "flat_v": flat_v, "dark": dark, "drift": drift,
            "raw": counts(expect * flat), "raw_vflat": counts(expect * flat_v),
            "flats": [counts(I0 * flat) for _ in range(10)],
            "darks": [counts(np.zeros((NV, NU))) for _ in range(10)]}


def write_fips(folder, frames, name="scan", keys=None, n=None):
    folder.mkdir(parents=True, exist_ok=True)
    step = 360.0 / N_VIEWS
    n = len(frames) if n is None else n
    values = {"NumberImages": n, "AngleFirst": 0.0, "AngleInterval": step,
              "AngleLast": (n - 1) * step,
              "DistanceSourceDetector": DSD, "DistanceSourceOrigin": DSO, "PixelSize": PX,
              "Exposure": "200 ms"}
    values.update(keys or {})
    txt = folder / f"{name}.txt"
    txt.write_text("".join(f"{k} = {v}\n" for k, v in values.items() if v is not None))
    for i, img in enumerate(frames):
        tifffile.imwrite(folder / f"{name}_{i + 1:04d}.tif", img)
    return txt


def write_frames(folder, prefix, frames):
    folder.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(frames):
        tifffile.imwrite(folder / f"{prefix}_{i:02d}.tif", img)
    return str(folder / f"{prefix}_*.tif")


def noise_std(scan, which="raw"):
    """Expected std of -log of the counts (Poisson + electronic noise), per pixel."""
    mean = I0 * scan["drift"][:, None, None] * np.exp(-scan["p"]) * (
        scan["flat"] if which == "raw" else scan["flat_v"])
    return np.sqrt(mean + 9.0 + 1 / 12) / mean


@pytest.fixture(scope="module")
def imported(scan, tmp_path_factory):
    root = tmp_path_factory.mktemp("raw")
    txt = write_fips(root / "scan", scan["raw"])
    flats = write_frames(root / "flats", "flat", scan["flats"])
    darks = write_frames(root / "darks", "dark", scan["darks"])
    out = root / "case"
    rec = import_scan(txt, out, flats=flats, darks=darks, cor="auto", nVoxel=24,
                      sVoxel=SIDE, reference="fdk-all", check=True)
    return root, out, rec


def test_flats_darks_recover_line_integrals(scan, imported):
    _, out, rec = imported
    case = load_case(out, rescale=False)
    assert case.info["units"] == {"length": "mm", "density": "1/mm", "normalised": False}
    assert case.geometry.n_views == N_VIEWS and case.test is None or case.test.size == 0
    err = case.train - scan["p"]
    sigma = noise_std(scan)
    # to the noise level: the flats' own noise (10 frames) adds ~5 % to the variance
    assert np.sqrt(np.mean(err ** 2)) <= 1.15 * np.sqrt(np.mean(sigma ** 2))
    # no bias (the source's 5 % drift would give 0.05): where the object is, away from
    # the clipping of negatives
    inside = scan["p"] > 0.1
    assert abs(np.mean(err[inside])) < 0.2 * np.sqrt(np.mean(sigma[inside] ** 2))
    assert rec["normalisation"]["method"] == "flats/darks"
    assert len(rec["normalisation"]["free_ray_columns"]) >= 4


def test_cor_auto_recovers_the_shift(imported):
    _, out, rec = imported
    assert abs(rec["cor"]["pixels"] - SHIFT_PX) <= 0.5
    assert rec["cor"]["uncertainty_pixels"] < 0.5
    meta = json.loads((out / "meta_data.json").read_text())
    assert meta["scanner"]["offDetector"][1] == pytest.approx(rec["cor"]["pixels"] * PX)
    assert (out / "check.png").stat().st_size > 1000
    assert json.loads((out / "import.json").read_text())["source"]["unknown_keys"] == \
        {"Exposure": "200 ms"}


def test_cor_from_a_shift_on_both_sides():
    """The symmetry estimate on exact projections, shifted either way (no noise), also
    with an object wider than the field of view (truncated projections)."""
    for shift, side in ((-2.6, SIDE), (0.0, SIDE), (4.3, 2 * SIDE)):
        geo = true_geometry(shift=shift).replace(sVoxel=(side,) * 3)
        p = make_phantom("shepp").line_integrals(geo)
        uc, _ = estimate_cor(p, geo.angles)
        assert abs((NU / 2 - uc) - shift) <= 0.1, (shift, side)


def test_fdk_of_import_matches_true_normalisation(scan, imported):
    _, out, _ = imported
    case = load_case(out, rescale=False)
    geo = true_geometry()
    gt = K * make_phantom("shepp").voxelize(geo)
    raw = scan["raw"].astype(np.float64)
    i0 = I0 * scan["drift"][:, None, None] * scan["flat"]
    p_true = np.maximum(-np.log(np.maximum(raw - scan["dark"], 0.5) / i0), 0)
    ref = fdk(p_true.astype(np.float32), geo)
    mine = fdk(case.train, case.geometry)
    r_ref = psnr_3d(ref, gt, gt.max())
    r_mine = psnr_3d(mine, gt, gt.max())
    assert r_mine >= r_ref - 0.5, (r_mine, r_ref)
    # and the geometry matters: the same counts with the shift ignored are much worse
    bad = fdk(case.train, case.geometry.replace(offDetector=(0.0, 0.0)))
    assert psnr_3d(bad, gt, gt.max()) < r_ref - 2
    # the pseudo ground truth is the FDK of all views, labelled so
    assert "FDK of all 60" in case.info["reference"]
    np.testing.assert_allclose(case.vol_gt, mine, atol=1e-4 * np.abs(mine).max())


def test_free_ray_normalisation_without_flats(scan, tmp_path):
    """I0 per view from the border columns: drift and vertical shading removed."""
    txt = write_fips(tmp_path / "s", scan["raw_vflat"])
    darks = write_frames(tmp_path / "d", "dark", scan["darks"])
    rec = import_scan(txt, tmp_path / "case", darks=darks, cor=SHIFT_PX, nVoxel=16,
                      train_views=20, test_views=10, seed=3)
    case = load_case(tmp_path / "case", rescale=False)
    assert rec["normalisation"]["method"] == "free-ray I0 per view"
    idx = np.array(rec["views"]["train"])
    np.testing.assert_array_equal(idx, np.arange(0, 60, 3))
    test_idx = np.array(rec["views"]["test"])
    assert test_idx.size == 10 and not set(test_idx) & set(idx)
    np.testing.assert_allclose(case.test_angles, circular_angles(60)[test_idx])
    err = case.train - scan["p"][idx]
    sigma = noise_std(scan, "vflat")[idx]
    assert np.sqrt(np.mean(err ** 2)) <= 1.15 * np.sqrt(np.mean(sigma ** 2))
    assert case.geometry.offDetector[1] == pytest.approx(SHIFT_PX * PX)


def test_binning_sums_counts(scan, tmp_path):
    txt = write_fips(tmp_path / "s", scan["raw"])
    flats = write_frames(tmp_path / "f", "flat", scan["flats"])
    darks = write_frames(tmp_path / "d", "dark", scan["darks"])
    rec = import_scan(txt, tmp_path / "case", flats=flats, darks=darks, bin=2, cor="auto",
                      nVoxel=12)
    case = load_case(tmp_path / "case", rescale=False)
    assert case.geometry.nDetector == (NV // 2, NU // 2)
    assert case.geometry.dDetector == pytest.approx((2 * PX, 2 * PX))
    assert abs(rec["cor"]["pixels"] - SHIFT_PX) <= 0.5
    # binned transmission = mean of the 4 pixels' transmissions (flat-weighted): compare
    t = np.exp(-scan["p"]) * scan["flat"]
    tb = t.reshape(N_VIEWS, NV // 2, 2, NU // 2, 2).sum((2, 4))
    fb = scan["flat"].reshape(NV // 2, 2, NU // 2, 2).sum((1, 3))
    assert np.sqrt(np.mean((case.train + np.log(tb / fb)) ** 2)) < 0.02


def test_normalise_floors_and_clips():
    raw = np.array([[[50.0, 200.0, 1150.0, 1000.0]]])
    p, rec = normalise(raw, dark=np.full((1, 4), 100.0), flat=np.full((1, 4), 1100.0))
    assert rec["floored_counts"] == 1 and rec["negative_clipped"] == 1
    assert np.all(np.isfinite(p)) and p.min() == 0
    assert p[0, 0, 1] == pytest.approx(np.log(10.0))


def test_naf_pickle(tmp_path):
    geo = true_geometry(n_vox=16)
    ph = make_phantom("shepp")
    tr, va = circular_angles(20), circular_angles(10) + 0.1
    data = {"DSD": DSD, "DSO": DSO, "nDetector": [NV, NU], "dDetector": [PX, PX],
            "nVoxel": [16, 16, 16], "dVoxel": [SIDE / 16] * 3, "offOrigin": [0, 0, 0],
            "offDetector": [0.0, SHIFT_PX * PX], "totalAngle": 360.0, "startAngle": 0.0,
            "accuracy": 0.5, "mode": "cone", "numTrain": 20, "numVal": 10,
            # NAF's generator: lengths in mm, projections computed in metres
            "train": {"projections": K * 1e-3 * ph.line_integrals(geo, tr), "angles": tr},
            "val": {"projections": K * 1e-3 * ph.line_integrals(geo, va), "angles": va},
            "image": K * ph.voxelize(geo)}
    path = tmp_path / "scan.pickle"
    path.write_bytes(pickle.dumps(data))
    rec = import_scan(path, tmp_path / "case")
    case = load_case(tmp_path / "case", rescale=False)
    assert case.info["units"]["length"] == "m" and rec["source"]["kind"] == "naf-pickle"
    np.testing.assert_allclose(case.train, data["train"]["projections"], rtol=1e-6)
    np.testing.assert_allclose(case.test_angles, va)
    assert case.geometry.DSD == pytest.approx(DSD * 1e-3)
    assert case.geometry.offDetector == pytest.approx((0.0, SHIFT_PX * PX * 1e-3))
    np.testing.assert_allclose(case.vol_gt, data["image"], rtol=1e-6)
    # projections, geometry and image agree: the FDK lands on the image's scale
    rec_vol = fdk(np.concatenate([case.train, case.test]), case.geometry.with_angles(
        np.concatenate([tr, va])))
    inside = data["image"] > 0.5 * data["image"].max()
    assert np.median(rec_vol[inside] / data["image"][inside]) == pytest.approx(1.0, abs=0.15)
    import_scan(path, tmp_path / "case_fdk", reference="fdk-all")
    ref = load_case(tmp_path / "case_fdk", rescale=False)
    np.testing.assert_allclose(ref.vol_gt, rec_vol, atol=1e-4 * np.abs(rec_vol).max())
    assert "FDK of all 30" in ref.info["reference"]

    marker = tmp_path / "owned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"echo owned > {marker}",))
    bad = tmp_path / "evil.pickle"
    bad.write_bytes(pickle.dumps({**data, "x": Evil()}))
    with pytest.raises(DatasetError, match="refuses the type posix.system"):
        load_naf(bad)
    assert not marker.exists()   # refused before it ran
    objs = tmp_path / "objs.pickle"
    objs.write_bytes(pickle.dumps({**data, "x": np.array([{}], dtype=object)}))
    with pytest.raises(DatasetError):
        load_naf(objs)


# ---------------------------------------------------------------- bad input (CLI)
def _cli(args, capsys):
    from mi_grg.cli import main
    rc = main(["import", *map(str, args)])
    return rc, capsys.readouterr().err.strip()


@pytest.mark.parametrize("case", ["missing_key", "count", "sizes", "flats_dark", "unreadable",
                                  "pickle_types", "angle_last"])
def test_bad_input_one_line_exit_2_no_output(case, scan, tmp_path, capsys):
    frames = list(scan["raw"][:6])
    keys, n, flats, darks = {}, None, None, None
    if case == "missing_key":
        keys = {"DistanceSourceOrigin": None}
    elif case == "count":
        n = 7
    elif case == "sizes":
        frames[3] = frames[3][:, :40]
    elif case == "angle_last":
        keys = {"AngleLast": 100.0}
    src = write_fips(tmp_path / "s", frames, keys=keys, n=n)
    if case == "unreadable":
        (tmp_path / "s" / "scan_0004.tif").write_bytes(b"not a tiff")
    if case == "flats_dark":
        flats = write_frames(tmp_path / "f", "flat", [d // 2 for d in scan["darks"][:2]])
        darks = write_frames(tmp_path / "d", "dark", scan["darks"][:2])
    if case == "pickle_types":
        src = tmp_path / "x.pkl"
        src.write_bytes(pickle.dumps({"DSD": 1.0, "train": {1, 2}}))
    args = [src, "--out", tmp_path / "out"]
    if flats:
        args += ["--flats", flats, "--darks", darks]
    rc, err = _cli(args, capsys)
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    expect = {"missing_key": "DistanceSourceOrigin", "count": "NumberImages = 7",
              "sizes": "scan_0004.tif", "flats_dark": "flats", "unreadable": "scan_0004.tif",
              "pickle_types": "set", "angle_last": "AngleLast"}[case]
    file = {"flats_dark": "flats", "sizes": "scan_0004.tif",
            "unreadable": "scan_0004.tif"}.get(case, src.name)
    assert expect in err and file in err, err
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_cli_import_runs(scan, tmp_path, capsys):
    txt = write_fips(tmp_path / "s", scan["raw_vflat"])
    rc, err = _cli([txt, "--out", tmp_path / "case", "--cor", "auto", "--nVoxel", "16",
                    "--train-views", "30", "--test-views", "5"], capsys)
    assert rc == 0, err
    case = load_case(tmp_path / "case")
    assert case.geometry.n_views == 30 and len(case.test_angles) == 5


# ---------------------------------------------------------------- units
def test_psnr_data_range_in_physical_units(imported):
    from mi_grg.methods import reconstruct
    _, out, _ = imported
    _, m = reconstruct(out, "fdk")
    case = load_case(out)
    assert m["psnr_data_range"] == pytest.approx(float(case.vol_gt.max()))
    assert "max of the ground truth" in m["psnr_data_range_rule"]
    assert m["ground_truth"].startswith("pseudo ground truth")
    assert m["psnr_3d"] > 100   # fdk of the training views = the FDK-all reference here


@pytest.fixture(scope="module")
def small_physical_case():
    """A 16^3 shepp case marked as physical units (not normalised)."""
    from mi_grg.data.simulate import default_geometry, simulate_case
    case = simulate_case("shepp", default_geometry(n=16, det=24, views=16), np.zeros(0))
    case.info["units"] = {"length": "mm", "density": "1/mm", "normalised": False}
    return case


UNIT_RUNS = {"fdk": {}, "sart": {"n_iter": 3, "progress": False},
             "r2": {"iterations": 60, "n_points": 1000, "progress": False},
             "gr": {"iterations": 60, "n_points": 1000, "progress": False}}


@pytest.mark.parametrize("method", sorted(UNIT_RUNS))
def test_every_method_is_unit_independent(method, small_physical_case):
    """Projections x 1e-2 and x 1e2 (densities in other units): the same reconstruction,
    scaled, within 0.2 dB of PSNR on the normalised scale."""
    import dataclasses

    from mi_grg.methods import get_method, reconstruct
    base = small_physical_case
    gt = base.vol_gt
    psnr, scales = {}, {}
    for f in (1e-2, 1.0, 1e2):
        c = dataclasses.replace(base, train=base.train * np.float32(f), vol_gt=gt * f)
        vol, m = reconstruct(c, method, **UNIT_RUNS[method])
        psnr[f] = psnr_3d(vol / f, gt, 1.0)   # dB differences do not depend on the range
        scales[f] = m["unit_scale"]
        assert m["psnr_data_range"] == pytest.approx(f * gt.max(), rel=1e-6)
        assert m["psnr_3d"] == pytest.approx(psnr_3d(vol, gt * f, f * gt.max()), abs=1e-6)
    for f in (1e-2, 1e2):
        assert abs(psnr[f] - psnr[1.0]) <= 0.2, psnr
        assert scales[f] == pytest.approx(f * scales[1.0], rel=1e-4)
    if method == "gr":
        # the test can fail: run bare (no unit scaling) on densities x 1e-4, gr is another
        # reconstruction (here its absolute thresholds prune every Gaussian)
        c = dataclasses.replace(base, train=base.train * np.float32(1e-4))
        try:
            vol, _ = get_method(method)(c, **UNIT_RUNS[method])
            differs = abs(psnr_3d(vol / 1e-4, gt, 1.0) - psnr[1.0]) > 0.2
        except RuntimeError:
            differs = True
        assert differs


def test_tiff_stack_with_scene_xml_and_angles_file(scan, tmp_path):
    """Plain TIFF folder + scene XML (geometry, offsets) + irregular angles from a file."""
    from mi_grg.data.scene import Scan, scan_to_xml
    geo = true_geometry()
    (tmp_path / "scan.xml").write_text(scan_to_xml(Scan(geometry=geo)))
    folder = tmp_path / "tiffs"
    write_frames(folder, "p", scan["raw"][:40])
    flats = write_frames(tmp_path / "f", "flat", scan["flats"])
    darks = write_frames(tmp_path / "d", "dark", scan["darks"])
    # the scene's 60 angles do not fit 40 TIFFs: an error naming both
    with pytest.raises(DatasetError, match="40 TIFFs"):
        import_scan(folder, tmp_path / "bad", scene=tmp_path / "scan.xml", flats=flats,
                    darks=darks)
    degrees = np.degrees(geo.angles[:40])
    (tmp_path / "angles.txt").write_text("\n".join(f"{a:.10f}" for a in degrees))
    rec = import_scan(folder, tmp_path / "case", scene=tmp_path / "scan.xml", flats=flats,
                      darks=darks, angles=tmp_path / "angles.txt", nVoxel=16)
    case = load_case(tmp_path / "case", rescale=False)
    np.testing.assert_allclose(case.geometry.angles, geo.angles[:40], atol=1e-9)
    assert case.geometry.offDetector == pytest.approx(geo.offDetector)   # from the XML
    assert case.geometry.DSD == DSD and case.geometry.dDetector == pytest.approx((PX, PX))
    err = case.train - scan["p"][:40]
    assert np.sqrt(np.mean(err ** 2)) <= 1.15 * np.sqrt(np.mean(noise_std(scan)[:40] ** 2))
    assert rec["source"]["kind"] == "tiff+scene"


def test_unit_scale_is_idempotent_and_skips_normalised(small_physical_case):
    import dataclasses

    from mi_grg.data.units import data_range, scaled_case, unit_scale
    c = small_physical_case
    s = unit_scale(c)
    assert 0.5 < s < 2   # the FDK's robust maximum of a [0, 1] phantom
    scaled = scaled_case(c, s)
    assert unit_scale(scaled) == 1.0 and scaled_case(scaled, 1.0) is scaled
    np.testing.assert_allclose(scaled.train * s, c.train, rtol=1e-6)
    normalised = dataclasses.replace(c, info={})          # simulated data: no units block
    assert unit_scale(normalised) == 1.0
    assert data_range(normalised, c.vol_gt)[0] == 1.0
    assert data_range(c, 3 * c.vol_gt)[0] == pytest.approx(3 * c.vol_gt.max())
