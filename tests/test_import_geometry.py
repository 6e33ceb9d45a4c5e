"""``mi-grg import`` of other tools' geometry files (mi_grg.data.geometry_files): an ASTRA
vector file, an RTK geometry XML (written and read back by itk-rtk, the reference for the
frame mapping), a Nikon .xtekct file. References: the rows the scan was simulated with,
RTK's own source positions and detector matrices, the phantom's exact line integrals."""
import numpy as np
import pytest
import tifffile

import mi_grg
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.dataset import DatasetError
from mi_grg.data.orbits import wobbling
from mi_grg.data.phantoms import make_phantom
from mi_grg.data.raw_import import import_scan

pytestmark = pytest.mark.filterwarnings("ignore:builtin type:DeprecationWarning")

NV, NU, PX, I0 = 32, 40, 0.4, 2.0e4


def _circle(views=24):
    return Geometry(mode="cone", DSD=500.0, DSO=300.0, nDetector=(NV, NU),
                    sDetector=(NV * PX, NU * PX), nVoxel=(20,) * 3, sVoxel=(8.0,) * 3,
                    angles=circular_angles(views))


def _write_frames(folder, geo, name="proj"):
    """Float32 counts I0 exp(-p) of the phantom's exact line integrals, and one flat."""
    folder.mkdir(parents=True, exist_ok=True)
    p = 0.25 * make_phantom("shepp").line_integrals(geo)
    for i, img in enumerate(I0 * np.exp(-p)):
        tifffile.imwrite(folder / f"{name}_{i + 1:04d}.tif", img.astype(np.float32))
    (folder.parent / "flats").mkdir(exist_ok=True)
    tifffile.imwrite(folder.parent / "flats" / "flat.tif", np.full((NV, NU), I0, np.float32))
    return p


def test_astra_vector_file(tmp_path):
    geo = wobbling(_circle())
    p = _write_frames(tmp_path / "scan", geo)
    rows = geo.view_vectors()
    (tmp_path / "geo").mkdir()
    np.savetxt(tmp_path / "geo" / "geom.vec", rows, header="ASTRA cone_vec rows")
    import_scan(tmp_path / "scan", tmp_path / "case", geometry=tmp_path / "geo" / "geom.vec",
                flats=str(tmp_path / "flats" / "flat.tif"), free_ray="none", nVoxel=20)
    case = mi_grg.load_case(tmp_path / "case", rescale=False)
    np.testing.assert_allclose(case.geometry.view_vectors(), rows, rtol=0, atol=1e-12)
    np.testing.assert_allclose(case.train, p, atol=1e-4)
    # a bad row names its line and view
    bad = rows.copy()
    (tmp_path / "geo" / "bad.vec").write_text("\n".join(" ".join(map(str, r)) for r in bad[:3])
                                      + "\n1 2 3\n")
    with pytest.raises(DatasetError, match=r"bad.vec: line 4 \(view 3\): expected 12"):
        import_scan(tmp_path / "scan", tmp_path / "c2", geometry=tmp_path / "geo" / "bad.vec")


def _rtk_random_geometry(rtk, n, rng):
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for i in range(n):
        g.AddProjection(300 + rng.uniform(-3, 3), 500 + rng.uniform(-5, 5),
                        float(i * 360.0 / n), rng.uniform(-1, 1), rng.uniform(-1, 1),
                        rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-1, 1),
                        rng.uniform(-1, 1))
    return g


def test_rtk_geometry_xml_maps_rtk_frames(tmp_path):
    from test_voxel_projector import rtk_or_skip
    from mi_grg.data.geometry_files import read_rtk_geometry
    itk, rtk = rtk_or_skip()
    g = _rtk_random_geometry(rtk, 6, np.random.default_rng(0))
    w = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    w.SetFilename(str(tmp_path / "g.xml"))
    w.SetObject(g)
    w.WriteFile()
    mode, rows, angles = read_rtk_geometry(tmp_path / "g.xml", (0.5, 0.4), (NV, NU))
    to_ours = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0]])   # (X, Y, Z) -> (Z, X, -Y)
    for i in range(6):
        M = np.array(itk.array_from_matrix(g.GetProjectionCoordinatesToFixedSystemMatrix(i)))
        d0 = M @ [0, 0, 0, 1.0]
        np.testing.assert_allclose(rows[i, 0:3], to_ours @ np.array(g.GetSourcePosition(i))[:3],
                                   atol=1e-9)
        np.testing.assert_allclose(rows[i, 3:6], to_ours @ d0[:3], atol=1e-9)
        np.testing.assert_allclose(rows[i, 6:9], to_ours @ (M @ [0.4, 0, 0, 1.0] - d0)[:3],
                                   atol=1e-12)
        np.testing.assert_allclose(rows[i, 9:12], to_ours @ (M @ [0, 0.5, 0, 1.0] - d0)[:3],
                                   atol=1e-12)
    assert mode == "cone"
    np.testing.assert_allclose(angles, np.radians(np.arange(6) * 60.0))


def test_rtk_geometry_import(tmp_path):
    from test_voxel_projector import rtk_or_skip
    from mi_grg.data.geometry_files import read_rtk_geometry
    itk, rtk = rtk_or_skip()
    g = _rtk_random_geometry(rtk, 12, np.random.default_rng(1))
    w = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    (tmp_path / "geo").mkdir()
    w.SetFilename(str(tmp_path / "geo" / "g.xml"))
    w.SetObject(g)
    w.WriteFile()
    _, rows, angles = read_rtk_geometry(tmp_path / "geo" / "g.xml", (PX, PX), (NV, NU))
    geo = _circle(12).replace(angles=angles, vectors=rows)
    p = _write_frames(tmp_path / "scan", geo)
    with pytest.raises(DatasetError, match="needs --pixel-size"):
        import_scan(tmp_path / "scan", tmp_path / "c0", geometry=tmp_path / "geo" / "g.xml")
    import_scan(tmp_path / "scan", tmp_path / "case", geometry=tmp_path / "geo" / "g.xml",
                pixel_size=PX, flats=str(tmp_path / "flats" / "flat.tif"), free_ray="none", nVoxel=20)
    case = mi_grg.load_case(tmp_path / "case", rescale=False)
    np.testing.assert_allclose(case.geometry.view_vectors(), rows, atol=1e-9)
    np.testing.assert_allclose(case.train, p, atol=1e-4)


def test_nikon_xtekct(tmp_path, capsys):
    geo = _circle(20).replace(offDetector=(0.2, -0.6), angles=np.radians(
        10.0 + np.arange(20) * 18.0))
    p = _write_frames(tmp_path / "scan", geo, name="part")
    (tmp_path / "scan" / "part.xtekct").write_text(
        "[XTekCT]\nName=part\nSrcToObject=300\nSrcToDetector=500\n"
        f"DetectorPixelsX={NU}\nDetectorPixelsY={NV}\nDetectorPixelSizeX={PX}\n"
        f"DetectorPixelSizeY={PX}\nDetectorOffsetX=-0.6\nDetectorOffsetY=0.2\n"
        "Projections=20\nInitialAngle=10\nAngularStep=18\nVoxelsX=20\n"
        "CentreOfRotationTop=0.25\nObjectTilt=0\nObjectRoll=0.0\n")
    rec = import_scan(tmp_path / "scan" / "part.xtekct", tmp_path / "case",
                      flats=str(tmp_path / "flats" / "flat.tif"), free_ray="none", nVoxel=20)
    # an alignment key the reader does not apply is said, not dropped; zeros are not
    assert rec["source"]["not_used"] == {"CentreOfRotationTop": "0.25"}
    err = capsys.readouterr().err
    assert "CentreOfRotationTop = 0.25: not applied" in err and "--cor auto" in err
    assert "ObjectTilt" not in err
    case = mi_grg.load_case(tmp_path / "case", rescale=False)
    g = case.geometry
    assert (g.DSD, g.DSO, g.nDetector, g.offDetector) == (500.0, 300.0, (NV, NU), (0.2, -0.6))
    np.testing.assert_allclose(g.angles, geo.angles, atol=1e-12)
    np.testing.assert_allclose(case.train, p, atol=1e-4)
    (tmp_path / "scan" / "part.ang").write_text("Projection\tAngle\n" + "".join(
        f"{i + 1}\t{a}\n" for i, a in enumerate(range(19))))
    with pytest.raises(DatasetError, match=r"part.ang: 19 angles for 20 projections"):
        import_scan(tmp_path / "scan" / "part.xtekct", tmp_path / "c2")
