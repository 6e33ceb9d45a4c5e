"""Volume files for CT tools (mi_grg.data.export): each file is read back with its own
library (tifffile, nibabel, ITK) and checked for values, voxel size, unit, origin and
orientation on an asymmetric volume with one marked voxel; reconstruct and import write
them; --format is validated."""
from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from mi_grg.data.export import DEFAULT_FORMATS, parse_formats, write_volume

# An asymmetric box: 5 x 7 x 4 voxels of 0.5 x 0.25 x 2 mm, centred at (1, -2, 3) mm.
SHAPE = (5, 7, 4)
GEO = {"nVoxel": [5, 7, 4], "sVoxel": [2.5, 1.75, 8.0], "offOrigin": [1.0, -2.0, 3.0]}
SPACING = (0.5, 0.25, 2.0)
MARK = (1, 5, 3)                 # [x, y, z] index of the marked voxel
# Its centre, worked out by hand: offOrigin - sVoxel / 2 + (index + 0.5) * spacing.
MARK_WORLD = (1.0 - 1.25 + 0.75, -2.0 - 0.875 + 1.375, 3.0 - 4.0 + 7.0)   # (0.5, -1.5, 6)
ORIGIN = (1.0 - 1.25 + 0.25, -2.0 - 0.875 + 0.125, 3.0 - 4.0 + 1.0)       # voxel (0, 0, 0)


@pytest.fixture
def volume():
    vol = np.arange(np.prod(SHAPE), dtype=np.float32).reshape(SHAPE) / 10
    vol[MARK] = 99.0
    return vol


@pytest.fixture
def written(volume, tmp_path):
    paths = write_volume(tmp_path, "vol", volume, GEO, "mm", ("npy", "tiff", "nifti"))
    return {p.name: p for p in paths}


def test_tiff_reads_back_in_imagej_layout(volume, written):
    with tifffile.TiffFile(written["vol.tif"]) as tif:
        assert tif.is_imagej
        data = tif.asarray()
        meta = tif.imagej_metadata
        page = tif.pages[0]
        xres = page.tags["XResolution"].value
        yres = page.tags["YResolution"].value
    assert data.dtype == np.float32 and data.shape == (4, 7, 5)      # ZYX: pages are z
    assert data[3, 5, 1] == 99.0                                     # [z, y, x] of MARK
    np.testing.assert_array_equal(data, volume.transpose(2, 1, 0))
    assert meta["slices"] == 4 and meta["unit"] == "mm"
    assert meta["spacing"] == pytest.approx(2.0)
    assert xres[0] / xres[1] == pytest.approx(1 / 0.5)               # pixels per mm
    assert yres[0] / yres[1] == pytest.approx(1 / 0.25)
    # ImageJ's calibration: world = (index - origin) * spacing
    for i, (key, d) in enumerate(zip(("xorigin", "yorigin", "zorigin"), SPACING)):
        assert (MARK[i] - meta[key]) * d == pytest.approx(MARK_WORLD[i])


def test_nifti_reads_back_with_spacing_origin_and_ras_axes(volume, written):
    import nibabel as nib
    img = nib.load(written["vol.nii.gz"])
    np.testing.assert_array_equal(np.asarray(img.dataobj), volume)   # [x, y, z] unchanged
    assert img.header.get_zooms() == pytest.approx(SPACING)
    assert img.header.get_xyzt_units()[0] == "mm"
    assert nib.aff2axcodes(img.affine) == ("R", "A", "S")
    assert int(img.header["qform_code"]) == 1 and int(img.header["sform_code"]) == 1
    np.testing.assert_allclose(img.affine @ [*MARK, 1], [*MARK_WORLD, 1])
    np.testing.assert_allclose(img.get_qform() @ [0, 0, 0, 1], [*ORIGIN, 1])


def test_nifti_in_itk_is_the_same_object_in_lps(volume, written):
    """ITK (and so 3D Slicer's readers) turns NIfTI's RAS into LPS: x and y negate."""
    itk = pytest.importorskip("itk")
    img = itk.imread(str(written["vol.nii.gz"]))
    arr = itk.array_from_image(img)                                  # [z, y, x]
    np.testing.assert_array_equal(arr, volume.transpose(2, 1, 0))
    assert tuple(img.GetSpacing()) == pytest.approx(SPACING)
    assert tuple(img.GetOrigin()) == pytest.approx((-ORIGIN[0], -ORIGIN[1], ORIGIN[2]))
    np.testing.assert_allclose(itk.array_from_matrix(img.GetDirection()),
                               np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    point = img.TransformIndexToPhysicalPoint([int(i) for i in MARK])   # ITK index (i, j, k)
    assert tuple(point) == pytest.approx((-MARK_WORLD[0], -MARK_WORLD[1], MARK_WORLD[2]))


def test_npy_is_the_array(volume, written):
    np.testing.assert_array_equal(np.load(written["vol.npy"]), volume)


def test_nifti_unit_names(volume, tmp_path):
    import nibabel as nib
    for unit, code in (("m", "meter"), ("normalised", "unknown")):
        write_volume(tmp_path, unit, volume, GEO, unit, "nifti")
        assert nib.load(tmp_path / f"{unit}.nii.gz").header.get_xyzt_units()[0] == code
    write_volume(tmp_path, "norm", volume, GEO, "normalised", "tiff")
    assert tifffile.TiffFile(tmp_path / "norm.tif").imagej_metadata["unit"] == "normalised"


def test_parse_formats():
    assert parse_formats(None) == DEFAULT_FORMATS == ("npy", "tiff")
    assert parse_formats("nifti,tiff") == ("nifti", "tiff")
    assert parse_formats(["npy", "tiff,nifti", "npy"]) == ("npy", "tiff", "nifti")
    with pytest.raises(ValueError, match=r"unknown format 'nrrd'; choose from npy, tiff, nifti"):
        parse_formats(["npy", "nrrd"])
    with pytest.raises(ValueError, match="no format given"):
        parse_formats(",")


def _zeros_method(case):
    return np.zeros(case.geometry.nVoxel, np.float32)


def test_reconstruct_writes_the_chosen_formats(tmp_path, small_cone_geometry):
    from mi_grg.data.case import Case
    from mi_grg.methods import METHODS, reconstruct
    METHODS["export-zeros"] = _zeros_method
    try:
        geo = small_cone_geometry
        case = Case(geometry=geo, train=np.zeros(geo.projection_shape, np.float32))
        reconstruct(case, "export-zeros", tmp_path / "default")
        assert sorted(p.name for p in (tmp_path / "default").glob("vol_pred*")) == \
            ["vol_pred.npy", "vol_pred.tif"]
        reconstruct(case, "export-zeros", tmp_path / "nii", formats="nifti")
        assert sorted(p.name for p in (tmp_path / "nii").glob("vol_pred*")) == \
            ["vol_pred.nii.gz"]
        with pytest.raises(ValueError, match="unknown format 'png'"):
            reconstruct(case, "export-zeros", tmp_path / "bad", formats="png")
        assert not (tmp_path / "bad").exists()
    finally:
        del METHODS["export-zeros"]
    with tifffile.TiffFile(tmp_path / "default" / "vol_pred.tif") as tif:
        # normalised data: 2 units over 16 voxels
        assert tif.imagej_metadata["spacing"] == pytest.approx(2.0 / 16)
        assert tif.imagej_metadata["unit"] == "normalised"


def test_cli_format_error_is_one_line_before_any_work(tmp_path, capsys):
    from mi_grg.cli import main
    rc = main(["reconstruct", str(tmp_path / "missing"), "--method", "fdk",
               "--format", "npy,jpeg", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert "unknown format 'jpeg'; choose from npy, tiff, nifti" in err
    assert not (tmp_path / "out").exists()


def test_import_writes_reference_in_mm(tmp_path):
    """A tiny FIPS scan (free-ray normalisation) imported with --reference fdk-all."""
    import nibabel as nib
    from mi_grg.core.geometry import Geometry, circular_angles
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.data.raw_import import import_scan
    n_det, px, side = 32, 0.4, 6.0                       # pixels, mm, mm
    geo = Geometry(mode="cone", DSD=500.0, DSO=300.0, nDetector=(n_det, n_det),
                   sDetector=(n_det * px,) * 2, nVoxel=(12,) * 3, sVoxel=(side,) * 3,
                   angles=circular_angles(16))
    counts = 2e4 * np.exp(-0.2 * make_phantom("shepp").line_integrals(geo))
    (tmp_path / "scan").mkdir()
    for i, frame in enumerate(counts):
        tifffile.imwrite(tmp_path / "scan" / f"s_{i + 1:04d}.tif", frame.astype(np.uint16))
    txt = tmp_path / "scan" / "s.txt"
    txt.write_text(f"NumberImages = 16\nAngleFirst = 0\nAngleInterval = 22.5\n"
                   f"AngleLast = 337.5\nDistanceSourceDetector = 500\n"
                   f"DistanceSourceOrigin = 300\nPixelSize = {px}\n")
    import_scan(txt, tmp_path / "case", nVoxel=12, sVoxel=side, reference="fdk-all")
    case_dir = tmp_path / "case"
    gt = np.load(case_dir / "vol_gt.npy")
    scanner = json.loads((case_dir / "meta_data.json").read_text())["scanner"]
    d = scanner["sVoxel"][0] / scanner["nVoxel"][0]
    assert d == pytest.approx(side / 12)
    with tifffile.TiffFile(case_dir / "vol_gt.tif") as tif:
        np.testing.assert_array_equal(tif.asarray(), gt.transpose(2, 1, 0))
        assert tif.imagej_metadata["unit"] == "mm"
        assert tif.imagej_metadata["spacing"] == pytest.approx(d)
    img = nib.load(case_dir / "vol_gt.nii.gz")
    np.testing.assert_array_equal(np.asarray(img.dataobj), gt)
    assert img.header.get_zooms() == pytest.approx((d,) * 3)
    assert img.header.get_xyzt_units()[0] == "mm"
