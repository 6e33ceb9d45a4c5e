"""Scene XML files, the ct_scanner sensor and the ct_phantom medium.

References: the float64 rays of ``Geometry.pixel_rays_numpy`` (whose conventions
test_geometry.py checks by hand), the closed-form phantom line integrals of
``mi_grg.data.phantoms`` and Mitsuba's own path tracer ``volpath``.
"""
import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

import mi_grg
from mi_grg.core.geometry import GeometryError, circular_angles
from mi_grg.data.scene import (SCANNER_FIELDS, Scan, ScanError, load_mitsuba_scene, load_scan,
                          parse_scanner_fields, scan_to_xml, write_scan_xml)

import drjit as dr  # noqa: E402  (after mi_grg: LLVM path)
import mitsuba as mi  # noqa: E402

SCENES = Path(__file__).resolve().parents[1] / "scenes"
# scenes/ may also hold non-Mitsuba files (training configs); scene files have <scene>
SCENE_FILES = sorted(p for p in SCENES.glob("*.xml") if ET.parse(p).getroot().tag == "scene")

SCANNER = """
        <string name="mode" value="{mode}"/>
        <float name="DSD" value="7"/> <float name="DSO" value="5"/>
        <string name="nDetector" value="6 8"/> <string name="sDetector" value="3, 4"/>
        <string name="nVoxel" value="8 8 8"/> <string name="sVoxel" value="2 2 2"/>
"""


def _scene(extra="", mode="cone", angles='<integer name="views" value="3"/>', tail="",
           medium=""):
    return (f'<scene version="3.0.0"><sensor type="ct_scanner">{SCANNER.format(mode=mode)}'
            f'{angles}{extra}{medium}</sensor>{tail}</scene>')


def _write(tmp_path, text, name="scene.xml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_the_required_scenes_exist():
    names = {p.name for p in SCENE_FILES}
    assert {"shepp_cone.xml", "shepp_parallel.xml", "needles_cone_offset.xml"} <= names


@pytest.mark.parametrize("path", SCENE_FILES, ids=[p.name for p in SCENE_FILES])
def test_every_scene_loads(path):
    scene = mi.load_file(str(path))
    sensor = scene.sensors()[0]
    scan = load_scan(path)
    g = scan.geometry
    nv, nu = g.nDetector
    # film: the views stacked along the rows
    assert list(sensor.film().size()) == [nu, g.n_views * nv]
    np.testing.assert_array_equal(sensor.geometry.angles, g.angles)
    np.testing.assert_array_equal(sensor.test_angles, scan.test_angles)
    assert sensor.noise == scan.noise
    json.dumps(scan.info())   # JSON-ready
    assert scan.info()["scanner"]["DSD"] == g.DSD
    # the render cross-check scenes (mi_grg.evaluation.crosscheck) scan other object kinds
    assert scan.object.get("type") == "ct_phantom" or (
        path.name.endswith("_volpath.xml")
        and scan.object.get("type") in ("gaussian_medium", "heterogeneous"))


def test_offset_scene_has_an_offset():
    scan = load_scan(SCENES / "needles_cone_offset.xml")
    assert any(scan.geometry.offDetector)
    assert scan.object == {"type": "ct_phantom", "phantom": "needles", "seed": 0}


def _sensor_rays(sensor, jitter_seed=0):
    """sample_ray at a random point inside every film pixel -> float64 [view, v, u, 3]."""
    g = sensor.geometry
    nv, nu = g.nDetector
    rows = g.n_views * nv
    r, c = np.meshgrid(np.arange(rows), np.arange(nu), indexing="ij")
    rng = np.random.default_rng(jitter_seed)
    # anywhere inside the pixel (not on its far edge): the sensor snaps to the centre
    x = (c + rng.uniform(0.01, 0.99, c.shape)) / nu
    y = (r + rng.uniform(0.01, 0.99, r.shape)) / rows
    n = x.size
    ray, weight = sensor.sample_ray(mi.Float(np.zeros(n)), mi.Float(np.zeros(n)),
                                    mi.Point2f(mi.Float(x.ravel()), mi.Float(y.ravel())),
                                    mi.Point2f(0.5, 0.5), True)
    shape = (g.n_views, nv, nu, 3)
    o = np.stack([np.asarray(ray.o[i]) for i in range(3)], -1).reshape(shape)
    d = np.stack([np.asarray(ray.d[i]) for i in range(3)], -1).reshape(shape)
    return o.astype(np.float64), d.astype(np.float64), np.asarray(ray.maxt).reshape(shape[:3]), \
        np.asarray(weight)


@pytest.mark.parametrize("path", SCENE_FILES, ids=[p.name for p in SCENE_FILES])
def test_sensor_rays_are_the_geometry_rays(path, variant):
    sensor = load_mitsuba_scene(path).sensors()[0]
    g = sensor.geometry
    o, d, maxt, weight = _sensor_rays(sensor)
    o_ref, d_ref = g.pixel_rays_numpy()
    scale = g.DSD
    np.testing.assert_allclose(o, o_ref, atol=2e-6 * scale)
    np.testing.assert_allclose(d, d_ref, atol=2e-6)
    np.testing.assert_array_equal(weight, 1.0)
    # maxt reaches the detector and the far side of the volume's bounding sphere
    ln = np.linalg.norm(np.asarray(_pixels(g)) - o_ref, axis=-1)
    c = np.asarray(g.offOrigin)
    far = np.einsum("...i,...i", c - o_ref, d_ref) + 0.5 * np.linalg.norm(g.sVoxel)
    np.testing.assert_allclose(maxt, np.maximum(ln, far), rtol=1e-5)


def test_film_positions_give_exact_rays_on_a_tall_film(tmp_path, variant):
    """1500 views x 40 rows = 60000 film rows: pixel centres still map to their own rays."""
    text = _scene(angles='<integer name="views" value="1500"/>').replace(
        'value="6 8"', 'value="40 3"')
    sensor = load_mitsuba_scene(_write(tmp_path, text)).sensors()[0]
    pos = sensor.film_positions()
    n = dr.width(pos)
    assert n == 1500 * 40 * 3
    ray, _ = sensor.sample_ray(mi.Float(np.zeros(n)), mi.Float(np.zeros(n)), pos,
                               mi.Point2f(0.5, 0.5), True)
    o_ref, d_ref = sensor.geometry.pixel_rays_numpy()
    d = np.stack([np.asarray(ray.d[i]) for i in range(3)], -1).reshape(d_ref.shape)
    o = np.stack([np.asarray(ray.o[i]) for i in range(3)], -1).reshape(o_ref.shape)
    np.testing.assert_allclose(d, d_ref, atol=2e-6)
    np.testing.assert_allclose(o, o_ref, atol=2e-5)


def test_rays_run_past_a_detector_inside_the_volume(tmp_path):
    """With the detector plane cutting the volume, maxt covers the volume's far side."""
    text = _scene('<string name="offOrigin" value="0.2 0 -0.1"/>').replace(
        'name="DSD" value="7"', 'name="DSD" value="5.5"')
    sensor = load_mitsuba_scene(_write(tmp_path, text)).sensors()[0]
    g = sensor.geometry
    o, d, maxt, _ = _sensor_rays(sensor)
    o_ref, d_ref = g.pixel_rays_numpy()
    ln = np.linalg.norm(np.asarray(_pixels(g)) - o_ref, axis=-1)
    far = (np.einsum("...i,...i", np.asarray(g.offOrigin) - o_ref, d_ref)
           + 0.5 * np.linalg.norm(g.sVoxel))
    assert np.all(far > ln + 0.1)
    np.testing.assert_allclose(maxt, far, rtol=1e-5)


def _pixels(g):
    """Pixel centres [view, v, u, 3] from the detector frame (conventions)."""
    f = g.detector_frame()
    nv, nu = g.nDetector
    dv, du = g.dDetector
    sv = ((np.arange(nv) + 0.5 - nv / 2) * dv)[None, :, None, None]
    su = ((np.arange(nu) + 0.5 - nu / 2) * du)[None, None, :, None]
    return (f["center"][:, None, None] + sv * f["e_v"][:, None, None]
            + su * f["e_u"][:, None, None])


def _ray_integrator():
    """A tiny Python integrator whose AOVs are the camera ray (built per variant)."""
    class RayAOV(mi.SamplingIntegrator):
        def aov_names(self):
            return ["ox", "oy", "oz", "dx", "dy", "dz"]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return (mi.Spectrum(1.0), dr.full(mi.Bool, True),
                    [ray.o.x, ray.o.y, ray.o.z, ray.d.x, ray.d.y, ray.d.z])

        def to_string(self):
            return "RayAOV"
    return RayAOV(mi.Properties())


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_rendered_film_stacks_the_views(tmp_path, mode, variant):
    """mi.render through the sensor: film row view*nv + v, column u is the ray of [view, v, u]."""
    text = _scene('<string name="offDetector" value="0.1 -0.3"/>', mode=mode,
                  angles='<integer name="views" value="4"/><float name="start_angle" '
                         'value="20"/>')
    scene = load_mitsuba_scene(_write(tmp_path, text))
    sensor = scene.sensors()[0]
    img = np.asarray(mi.render(scene, spp=3, integrator=_ray_integrator()))
    assert img.shape[:2] == (4 * 6, 8)
    o_ref, d_ref = sensor.geometry.pixel_rays_numpy()
    o = np.stack([sensor.to_projections(img[..., 1 + i]) for i in range(3)], -1)
    d = np.stack([sensor.to_projections(img[..., 4 + i]) for i in range(3)], -1)
    np.testing.assert_allclose(o, o_ref, atol=1e-5)
    np.testing.assert_allclose(d, d_ref, atol=1e-5)
    np.testing.assert_allclose(sensor.geometry.angles, np.radians(20) + np.arange(4) * np.pi / 2)


def test_scene_with_sensor_and_integrator_only(tmp_path):
    """Mitsuba accepts a scan with no shapes and no emitters; rays that hit nothing give 0."""
    scene = mi.load_string(_scene(tail='<integrator type="volpath"/>'))
    assert len(scene.shapes()) == 0 and len(scene.emitters()) == 0
    img = np.asarray(mi.render(scene, spp=1))
    assert img.shape[:2] == (3 * 6, 8) and np.all(img == 0)


def test_volpath_transmittance_matches_the_closed_form(variant):
    """Mitsuba's path tracer through ct_scanner + ct_phantom vs exact line integrals."""
    from mi_grg.data.phantoms import make_phantom
    path = SCENES / "shepp_cone_volpath.xml"
    scene = load_mitsuba_scene(path)
    sensor = scene.sensors()[0]
    spp = 256
    img = sensor.to_projections(mi.render(scene, spp=spp, seed=1))
    ref = np.exp(-make_phantom("shepp").line_integrals(sensor.geometry))
    # rays that miss the phantom see exactly 1
    air = ref == 1.0
    np.testing.assert_array_equal(img[air], 1.0)
    # elsewhere each sample is a 0/1 survival indicator (albedo 0): binomial noise
    m = (ref > 0.02) & (ref < 0.98)
    z = (img[m] - ref[m]) / np.sqrt(ref[m] * (1 - ref[m]) / spp)
    assert np.abs(z).max() < 5.5
    assert abs(z.mean()) < 5 / math.sqrt(z.size)      # no bias
    assert 0.8 < z.std() < 1.2
    assert m.sum() > 500 and air.sum() > 100           # the phantom is in view, and air too


# ------------------------------------------------------------------ bad inputs
def _load_error(tmp_path, text, exc=(ScanError, GeometryError, RuntimeError)):
    p = _write(tmp_path, text)
    with pytest.raises(exc) as e1:
        mi.load_file(str(p))
    with pytest.raises((ScanError, GeometryError)) as e2:
        load_scan(p)
    return str(e1.value), str(e2.value)


def test_misspelled_parameter(tmp_path):
    for msg in _load_error(tmp_path, _scene('<float name="DSOO" value="5"/>')):
        assert "DSOO" in msg and "did you mean 'DSO'" in msg
    for msg in _load_error(tmp_path, _scene('<integer name="test_view" value="5"/>')):
        assert "test_view" in msg and "test_views" in msg


@pytest.mark.parametrize("extra,names", [
    ('<float name="I0" value="1000"/>', ["I0"]),
    ('<string name="noise" value="none"/><float name="electronic_std" value="3"/>',
     ["electronic_std"]),
    ('<integer name="noise_seed" value="4"/><boolean name="clip_negative" value="false"/>',
     ["noise_seed", "clip_negative"]),
])
def test_noise_parameters_without_noise(tmp_path, extra, names):
    for msg in _load_error(tmp_path, _scene(extra)):
        assert all(n in msg for n in names) and "poisson+gaussian" in msg


def test_noise_model(tmp_path):
    scan = load_scan(_write(tmp_path, _scene('<string name="noise" value="poisson+gaussian"/>')))
    assert scan.noise == {"model": "poisson+gaussian", "I0": 1e4, "electronic_std": 10.0,
                          "seed": 0, "clip_negative": True}
    scan = load_scan(_write(tmp_path, _scene(
        '<string name="noise" value="poisson+gaussian"/><float name="I0" value="500"/>'
        '<float name="electronic_std" value="0"/><integer name="noise_seed" value="7"/>'
        '<boolean name="clip_negative" value="false"/>')))
    assert scan.noise == {"model": "poisson+gaussian", "I0": 500.0, "electronic_std": 0.0,
                          "seed": 7, "clip_negative": False}
    assert load_scan(_write(tmp_path, _scene())).noise is None
    for bad, name in [('<string name="noise" value="poisson"/>', "noise"),
                      ('<string name="noise" value="poisson+gaussian"/>'
                       '<float name="I0" value="0"/>', "I0"),
                      ('<string name="noise" value="poisson+gaussian"/>'
                       '<float name="electronic_std" value="-1"/>', "electronic_std")]:
        for msg in _load_error(tmp_path, _scene(bad)):
            assert name in msg


def test_angle_fields(tmp_path):
    both = _scene(angles='<integer name="views" value="3"/><string name="angles" value="0 1"/>')
    for msg in _load_error(tmp_path, both):
        assert "views" in msg and "angles" in msg and "not both" in msg
    arc_with_angles = _scene(angles='<string name="angles" value="0 1"/>'
                                    '<float name="total_angle" value="180"/>')
    for msg in _load_error(tmp_path, arc_with_angles):
        assert "total_angle" in msg
    for msg in _load_error(tmp_path, _scene(angles="")):
        assert "views" in msg and "angles" in msg
    tests = _scene('<integer name="test_views" value="2"/><string name="test_angles" value="1"/>')
    for msg in _load_error(tmp_path, tests):
        assert "test_views" in msg and "test_angles" in msg
    for bad, name in [('<integer name="views" value="0"/>', "views"),
                      ('<string name="angles" value=""/>', "angles"),
                      ('<string name="angles" value="0, nan"/>', "angles"),
                      ('<string name="angles" value="0, x"/>', "angles"),
                      ('<integer name="views" value="4"/><float name="total_angle" '
                       'value="400"/>', "total_angle")]:
        for msg in _load_error(tmp_path, _scene(angles=bad)):
            assert name in msg
    # explicit radians, comma or space separated; views with an arc in degrees
    scan = load_scan(_write(tmp_path, _scene(angles='<string name="angles" value="0.5, 1 2"/>')))
    np.testing.assert_array_equal(scan.geometry.angles, [0.5, 1.0, 2.0])
    scan = load_scan(_write(tmp_path, _scene(
        angles='<integer name="views" value="5"/><float name="total_angle" value="180"/>'
               '<float name="start_angle" value="-30"/><integer name="test_views" value="2"/>')))
    np.testing.assert_allclose(scan.geometry.angles, -np.pi / 6 + np.arange(5) * np.pi / 5,
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(scan.test_angles, -np.pi / 6 + (np.arange(2) + 0.5) * np.pi / 2,
                               rtol=0, atol=1e-15)
    # full circle: the brief's circular_angles(n) + pi / n, bit for bit
    scan = load_scan(_write(tmp_path, _scene('<integer name="test_views" value="7"/>')))
    np.testing.assert_array_equal(scan.test_angles, circular_angles(7) + np.pi / 7)
    np.testing.assert_array_equal(scan.geometry.angles, circular_angles(3))


def test_geometry_errors_name_the_field(tmp_path):
    for bad, name in [('<string name="offDetector" value="0 nan"/>', "offDetector"),
                      ('<string name="offOrigin" value="0 0"/>', "offOrigin")]:
        for msg in _load_error(tmp_path, _scene(bad)):
            assert name in msg
    text = _scene().replace('name="DSO" value="5"', 'name="DSO" value="7.5"')
    for msg in _load_error(tmp_path, text):
        assert "DSO" in msg
    text = _scene().replace('value="cone"', 'value="fan"')
    for msg in _load_error(tmp_path, text):
        assert "mode" in msg
    text = _scene().replace('<string name="nVoxel" value="8 8 8"/>', "")
    for msg in _load_error(tmp_path, text):
        assert "nVoxel" in msg


def test_child_objects(tmp_path):
    for child, word in [('<film type="hdrfilm"/>', "film"),
                        ('<sampler type="independent"/>', "sampler"),
                        ('<medium type="ct_phantom"><string name="phantom" value="shepp"/>'
                         '</medium><medium type="homogeneous"/>', "at most one")]:
        for msg in _load_error(tmp_path, _scene(medium=child)):
            assert word in msg.lower()
    # Mitsuba's to_world would be silently unused: refused
    tw = '<transform name="to_world"><translate x="1"/></transform>'
    for msg in _load_error(tmp_path, _scene(tw)):
        assert "to_world" in msg


def test_phantom_medium_errors(tmp_path):
    med = '<medium type="ct_phantom"><string name="phantom" value="{}"/>{}</medium>'
    for name, extra, words in [("shep", "", ["shep", "did you mean 'shepp'"]),
                               ("shepp", '<integer name="seed" value="3"/>', ["seed"]),
                               ("shells", '<integer name="sede" value="3"/>', ["sede", "seed"])]:
        text = _scene(medium=med.format(name, extra))
        p = _write(tmp_path, text)
        with pytest.raises(Exception) as e:
            load_scan(p)
        assert all(w in str(e.value) for w in words), str(e.value)
    # a phantom that no ct_scanner placed refuses to be used
    m = mi.load_dict({"type": "ct_phantom", "phantom": "shepp"})
    with pytest.raises(RuntimeError, match="ct_scanner"):
        m.density(mi.Point3f(0, 0, 0))


def test_phantom_medium_density_matches_numpy(tmp_path):
    """ct_phantom's Dr.Jit density == EllipsoidPhantom.density (float64 reference)."""
    from mi_grg.data.phantoms import make_phantom
    text = _scene('<string name="offOrigin" value="0.1 -0.2 0.05"/>',
                  medium='<medium type="ct_phantom"><string name="phantom" value="shells"/>'
                         '<integer name="seed" value="2"/></medium>')
    sensor = load_mitsuba_scene(_write(tmp_path, text)).sensors()[0]
    medium = sensor.get_medium()
    pts = np.random.default_rng(0).uniform(-1.1, 1.1, (20000, 3))
    got = np.asarray(medium.density(mi.Point3f(*[mi.Float(pts[:, i]) for i in range(3)])))
    want = make_phantom("shells", seed=2).density(pts, sensor.geometry)
    # float32 points: disagreement only right at ellipsoid surfaces
    assert np.mean(np.abs(got - want) > 1e-5) < 2e-3
    assert want.max() > 0.5


# ------------------------------------------------------------------ Scan round trip
def _same_scan(a: Scan, b: Scan):
    for name in ("mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel",
                 "offOrigin", "offDetector"):
        assert getattr(a.geometry, name) == getattr(b.geometry, name), name
    np.testing.assert_array_equal(a.geometry.angles, b.geometry.angles)
    np.testing.assert_array_equal(a.test_angles, b.test_angles)
    assert a.noise == b.noise and a.object == b.object and a.integrator == b.integrator
    assert a.other == b.other


@pytest.mark.parametrize("path", SCENE_FILES, ids=[p.name for p in SCENE_FILES])
def test_xml_round_trip(tmp_path, path):
    scan = load_scan(path)
    for data in (*SCENES.glob("*.npz"), *SCENES.glob("*.vol")):   # files the scenes name
        (tmp_path / data.name).write_bytes(data.read_bytes())
    _same_scan(scan, load_scan(write_scan_xml(scan, tmp_path / "rt.xml")))


def test_xml_round_trip_arbitrary(tmp_path, rng):
    geo = mi_grg.Geometry(mode="cone", DSD=1234.5678, DSO=987.654321, nDetector=(7, 9),
                          sDetector=(0.1 * math.pi, 123.456), nVoxel=(5, 6, 7),
                          sVoxel=(100 / 3, 200 / 7, 300 / 11), offOrigin=(1e-3, -2 / 3, 0.1),
                          offDetector=(-1 / 7, 2 / 9), angles=rng.uniform(-7, 7, 11))
    scan = Scan(geometry=geo, test_angles=rng.uniform(0, 7, 3),
                noise={"model": "poisson+gaussian", "I0": 1234.5, "electronic_std": 1 / 3},
                object={"type": "ct_phantom", "phantom": "needles", "seed": 7},
                integrator={"type": "volpath", "max_depth": 3, "hide_emitters": False},
                other=[{"type": "constant", "radiance": 0.5}])
    back = load_scan(write_scan_xml(scan, tmp_path / "rt.xml"))
    _same_scan(scan, back)
    assert back.path == str(tmp_path / "rt.xml")
    # full-circle grids are written as counts
    s2 = Scan(geometry=geo.with_angles(circular_angles(9)), test_angles=circular_angles(4)
              + np.pi / 4)
    text = scan_to_xml(s2)
    assert 'name="views" value="9"' in text and 'name="test_views" value="4"' in text
    _same_scan(s2, load_scan(_write(tmp_path, text, "s2.xml")))


def test_overrides(tmp_path):
    path = SCENES / "shepp_cone.xml"
    base = load_scan(path)
    s = load_scan(path, {"views": 10, "test_views": 0})
    np.testing.assert_array_equal(s.geometry.angles, circular_angles(10))
    assert s.test_angles.size == 0 and s.noise == base.noise
    s = load_scan(path, {"angles": [0.1, 0.2], "noise": "none"})
    np.testing.assert_array_equal(s.geometry.angles, [0.1, 0.2])
    assert s.noise is None
    s = load_scan(path, {"I0": 100.0})
    assert s.noise["I0"] == 100.0
    with pytest.raises(ScanError, match="viewz.*views"):
        load_scan(path, {"viewz": 10})
    with pytest.raises((ScanError, GeometryError), match="views"):
        load_scan(path, {"views": 0})
    # overrides are checked like XML values
    with pytest.raises((ScanError, GeometryError), match="DSO"):
        load_scan(path, {"DSO": 8.0})


def test_load_scan_file_errors(tmp_path):
    with pytest.raises(ScanError, match="does not exist"):
        load_scan(tmp_path / "missing.xml")
    with pytest.raises(ScanError):
        load_scan(_write(tmp_path, "<scene version='3.0.0'><sensor"))
    with pytest.raises(ScanError, match="ct_scanner"):
        load_scan(_write(tmp_path, '<scene version="3.0.0"><sensor type="perspective"/>'
                                   '</scene>'))
    two = _scene().replace("</scene>", '<sensor type="perspective"/></scene>')
    with pytest.raises(ScanError, match="exactly one sensor"):
        load_scan(_write(tmp_path, two))


def test_parse_scanner_fields_matches_the_xml_field_list():
    """Every documented field is accepted by the parser (and nothing else)."""
    fields = {"mode": "cone", "DSD": 7, "DSO": 5, "nDetector": "2 2", "sDetector": "1 1",
              "nVoxel": "2 2 2", "sVoxel": "1 1 1", "views": 2}
    geo, test, noise = parse_scanner_fields(fields)
    assert geo.n_views == 2 and test.size == 0 and noise is None
    assert set(SCANNER_FIELDS) == {
        "mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel", "offOrigin",
        "offDetector", "views", "total_angle", "start_angle", "angles", "test_views",
        "test_angles", "vectors", "test_vectors", "noise", "I0", "electronic_std", "noise_seed",
        "clip_negative"}
    docs = (Path(__file__).resolve().parents[1] / "docs" / "conventions.md").read_text()
    for name in SCANNER_FIELDS:
        assert f"`{name}`" in docs, f"docs/conventions.md does not describe {name}"
