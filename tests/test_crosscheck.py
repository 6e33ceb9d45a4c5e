"""Mitsuba volpath (Monte Carlo) vs exp(-projection), the gaussian_medium plugin and the
exact line integrals of voxel grids used as the grid route's reference."""
import json
from pathlib import Path

import numpy as np
import pytest

import mi_grg
import drjit as dr
import mitsuba as mi

from mi_grg.evaluation.crosscheck import (binomial_z, compare, integrate_volume,
                                          render_crosscheck, render_scene, view_statistics)
from mi_grg.evaluation.crosscheck_run import render_run
from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry


def tiny_case(rng, n=4):
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(16, 16), sDetector=(3.0, 3.0),
                   nVoxel=(32, 32, 32), sVoxel=(2.0, 2.0, 2.0), offOrigin=(0.1, 0.0, -0.05),
                   angles=[0.2, 1.4, 2.5])
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    params = {"pos": np.asarray(geo.offOrigin) + rng.uniform(-0.35, 0.35, (n, 3)),
              "scales": rng.uniform(0.1, 0.25, (n, 3)), "q": q, "rho": rng.uniform(0.3, 2.0, n)}
    g = Gaussians.from_numpy(params["pos"], params["scales"], params["q"], params["rho"])
    return g, geo, params


def field64(params, x, extent):
    """sum_i rho_i exp(-m^2/2) [m <= extent] at points x [M, 3], float64."""
    w, qx, qy, qz = params["q"].T
    R = np.stack([1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                  2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                  2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)],
                 -1).reshape(-1, 3, 3)
    cov = R @ (params["scales"][:, :, None] ** 2 * np.transpose(R, (0, 2, 1)))
    A = np.linalg.inv(cov)
    out = np.zeros(len(x))
    for i in range(len(A)):
        d = x - params["pos"][i]
        m2 = np.einsum("ni,ij,nj->n", d, A[i], d)
        out += np.where(m2 <= extent ** 2, params["rho"][i] * np.exp(-0.5 * m2), 0.0)
    return out


@pytest.fixture
def medium(tmp_path, rng):
    g, geo, params = tiny_case(rng)
    g.save_npz(tmp_path / "g.npz")
    mi_grg.set_variant(mi.variant())
    return mi.load_dict({"type": "gaussian_medium", "filename": str(tmp_path / "g.npz"),
                         "extent": 4.0}), params


# ---------------------------------------------------------------- gaussian_medium
def test_gaussian_medium_extinction_matches_numpy(medium, rng):
    med, params = medium
    x = params["pos"][rng.integers(0, 4, 4000)] + rng.normal(size=(4000, 3)) * 0.3
    p = mi.Point3f(*[mi.Float(x[:, k]) for k in range(3)])
    ref = field64(params, x, 4.0)
    np.testing.assert_allclose(np.asarray(med.sigma_t(p)), ref, rtol=2e-5, atol=1e-6 * ref.max())
    mei = dr.zeros(mi.MediumInteraction3f, 4000)
    mei.p = p
    sigma_s, sigma_n, sigma_t = med.get_scattering_coefficients(mei)
    np.testing.assert_allclose(np.asarray(sigma_t[0]), ref, rtol=2e-5, atol=1e-6 * ref.max())
    assert not np.asarray(sigma_s[0]).any()
    np.testing.assert_allclose(np.asarray(sigma_n[0]) + np.asarray(sigma_t[0]), med.majorant,
                               rtol=1e-6)
    assert not med.is_homogeneous() and not med.has_spectral_extinction()


def test_gaussian_medium_majorant_is_a_safe_bound(medium, rng):
    med, params = medium
    # dense samples around every centre, where the maxima are
    x = params["pos"][rng.integers(0, 4, 200000)] + rng.normal(size=(200000, 3)) * 0.15
    peak = field64(params, np.concatenate([x, params["pos"]]), 4.0).max()
    assert peak <= med.majorant <= params["rho"].sum() * (1 + 1e-5)
    assert med.majorant < 1.5 * peak   # and a useful one (few null collisions)
    m = med.get_majorant(dr.zeros(mi.MediumInteraction3f, 1))
    assert float(m[0][0]) == pytest.approx(med.majorant, rel=1e-6)


@pytest.mark.parametrize("max_entries", [None, 2000])
def test_gaussian_medium_cell_lists_sum_every_gaussian(tmp_path, rng, monkeypatch, max_entries):
    """Many Gaussians of mixed sizes: the per-cell sums equal the float64 sum over all of
    them (also when the grid is coarsened to fit MAX_CELL_ENTRIES), and the majorant from
    local sums bounds the field (loosely where many small Gaussians overlap)."""
    from mi_grg.plugins import gaussian_medium as gm
    if max_entries is not None:
        monkeypatch.setattr(gm, "MAX_CELL_ENTRIES", max_entries)
    n = 400
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    params = {"pos": rng.uniform(-0.8, 0.8, (n, 3)),
              "scales": np.exp(rng.uniform(np.log(0.02), np.log(0.3), (n, 3))), "q": q,
              "rho": rng.uniform(0.05, 1.0, n)}
    Gaussians.from_numpy(params["pos"], params["scales"], params["q"],
                         params["rho"]).save_npz(tmp_path / "g.npz")
    mi_grg.set_variant(mi.variant())
    med = mi.load_dict({"type": "gaussian_medium", "filename": str(tmp_path / "g.npz"),
                        "extent": 3.0})
    x = np.concatenate([params["pos"][rng.integers(0, n, 3000)] + rng.normal(size=(3000, 3))
                        * 0.2, rng.uniform(-1.5, 1.5, (1000, 3))])
    ref = field64(params, x, 3.0)
    got = np.asarray(med.sigma_t(mi.Point3f(*[mi.Float(x[:, k]) for k in range(3)])))
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=1e-6 * ref.max())
    entries = len(np.asarray(med._index))
    assert med._res > 1 and (max_entries is None or entries <= max_entries)
    peak = ref.max()      # the field's peak is about 3.0 (a 160^3 voxelisation)
    assert peak <= med.majorant
    if max_entries is None:  # local sums; one global Lipschitz bound gave ~143 here
        assert med.majorant < 6 * peak


def test_gaussian_medium_box(medium):
    med, params = medium
    lo, hi = np.asarray(med.bbox.min), np.asarray(med.bbox.max)
    assert np.all(lo < params["pos"].min(0)) and np.all(hi > params["pos"].max(0))
    ray = mi.Ray3f(mi.Point3f(-10, 0.05, 0.0), mi.Vector3f(1, 0, 0))
    hit, t0, t1 = med.intersect_aabb(ray)
    assert bool(hit[0])
    assert float(t0[0]) == pytest.approx(10 + lo[0], rel=1e-5)
    assert float(t1[0]) == pytest.approx(10 + hi[0], rel=1e-5)


# ---------------------------------------------------------------- grid line integrals
def test_integrate_volume_constant_is_chord_length():
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(9, 11), sDetector=(3.5, 3.5),
                   nVoxel=(6, 8, 5), sVoxel=(1.6, 2.0, 1.2), offOrigin=(0.1, -0.1, 0.05),
                   angles=[0.3, 2.0])
    proj = integrate_volume(np.full(geo.nVoxel, 0.7, np.float32), geo)
    o, d = geo.pixel_rays_numpy()
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    chord = np.maximum(np.maximum(t0, t1).min(-1) - np.maximum(np.minimum(t0, t1).max(-1), 0), 0)
    assert (chord > 0).any() and (chord == 0).any()
    np.testing.assert_allclose(proj, 0.7 * chord, rtol=1e-5, atol=1e-5)


def test_integrate_volume_matches_dense_trilinear_quadrature(rng):
    """Against scipy's trilinear interpolation (clamped at the edges) sampled densely."""
    from scipy.ndimage import map_coordinates
    geo = Geometry(mode="cone", DSD=6.0, DSO=4.0, nDetector=(5, 6), sDetector=(2.5, 2.5),
                   nVoxel=(7, 9, 6), sVoxel=(1.4, 1.8, 1.2), offOrigin=(0.0, 0.1, -0.1),
                   angles=[0.7])
    vol = rng.uniform(0, 1, geo.nVoxel).astype(np.float32)
    proj = integrate_volume(vol, geo)
    o, d = (a.reshape(-1, 3) for a in geo.pixel_rays_numpy())
    lo, hi = geo.bbox()
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    t_in, t_out = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    ref = np.zeros(len(o))
    s = (np.arange(20000) + 0.5) / 20000   # midpoint rule
    for i in np.nonzero(t_out > t_in)[0]:
        t = t_in[i] + s * (t_out[i] - t_in[i])
        x = o[i] + t[:, None] * d[i]
        idx = (x - lo) / np.asarray(geo.dVoxel) - 0.5   # voxel-centre index coordinates
        vals = map_coordinates(vol.astype(np.float64), idx.T, order=1, mode="nearest")
        ref[i] = vals.mean() * (t_out[i] - t_in[i])
    np.testing.assert_allclose(proj.ravel(), ref, rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------- Monte Carlo vs closed form
def test_volpath_agrees_with_the_projector(tmp_path, rng):
    g, geo, _ = tiny_case(rng)
    res = render_crosscheck((g, geo), spp=256, out_dir=tmp_path, seed=3)
    for route in ("gaussian", "grid"):
        s = res["routes"][route]
        assert abs(s["z_mean"]) < 4.0, (route, s)
        assert 0.75 < s["z_rms"] < 1.3, (route, s)
        assert s["pixels_used"] > 300
    # the grid route's reference differs from the closed form only by discretisation
    assert res["routes"]["grid"]["grid_vs_projector"]["max_abs_T_difference"] < 0.05
    saved = json.loads((tmp_path / "crosscheck.json").read_text())
    assert saved["routes"]["gaussian"]["z_mean"] == res["routes"]["gaussian"]["z_mean"]
    for name in ("projector_T", "mc_gaussian", "diff_gaussian", "grid_T", "mc_grid",
                 "diff_grid"):
        assert (tmp_path / f"{name}.png").stat().st_size > 0
        img = np.asarray(mi.Bitmap(str(tmp_path / f"{name}.exr")))
        assert img.shape[:2] == (3 * 16, 16)


def test_monte_carlo_error_shrinks_as_one_over_sqrt_spp(tmp_path, rng):
    g, geo, _ = tiny_case(rng)
    rms = {}
    for spp in (64, 1024):
        res = render_crosscheck((g, geo), spp=spp, out_dir=tmp_path / str(spp), seed=11)
        rms[spp] = {r: s["rms_error"] for r, s in res["routes"].items()}
    for route in ("gaussian", "grid"):
        ratio = rms[64][route] / rms[1024][route]
        assert 3.2 < ratio < 5.0, (route, ratio)   # sqrt(16) = 4


def test_a_biased_estimate_is_detected(rng):
    """The statistics can fail: a 1 % transmittance bias at 4096 spp is many sigmas."""
    t = rng.uniform(0.3, 0.9, (3, 16, 16))
    noisy = t + rng.normal(size=t.shape) * np.sqrt(t * (1 - t) / 4096)
    assert abs(compare(noisy, t, 4096)["z_mean"]) < 4.0
    assert abs(compare(noisy * 0.99, t, 4096)["z_mean"]) > 10.0


def test_scene_file_of_gaussians_is_rendered_as_written(tmp_path, rng):
    from mi_grg.data.scene import Scan, write_scan_xml
    g, geo, _ = tiny_case(rng, n=2)
    g.save_npz(tmp_path / "blobs.npz")
    mi_grg.set_variant(mi.variant())
    xml = write_scan_xml(Scan(geometry=geo, object={"type": "gaussian_medium",
                                                    "filename": "blobs.npz"},
                              integrator={"type": "volpath"},
                              other=[{"type": "constant", "radiance": 1.0}]),
                         tmp_path / "scan.xml")
    res = render_crosscheck(xml, spp=16, out_dir=tmp_path / "out")
    assert res["object"] == "gaussian_medium" and res["n_gaussians"] == 2
    assert res["projection_shape"] == [3, 16, 16] and len(res["views"]) == 3
    assert res["pass"], res["views"]


# ---------------------------------------------------------------- scene files, per object kind
SCENES = Path(__file__).resolve().parents[1] / "scenes"


@pytest.mark.parametrize("name, kind", [("shepp_cone_volpath.xml", "ct_phantom"),
                                        ("gaussians_cone_volpath.xml", "gaussian_medium"),
                                        ("shepp_grid_volpath.xml", "heterogeneous")])
def test_shipped_scene_of_each_object_kind_passes(tmp_path, name, kind):
    """volpath (Mitsuba's own delta tracking) against the independent exact reference of
    each kind; the statistics are those of a binomial count per pixel."""
    res = render_scene(SCENES / name, 64, tmp_path, seed=5)
    assert res["object"] == kind and res["pass"], res["views"]
    for v in res["views"]:
        assert 0.7 < v["z_rms"] < 1.3, v                  # errors are as large as predicted
        assert 0.7 < v["rms_difference"] / v["expected_rms_standard_error"] < 1.3, v
        assert v["pixels_informative"] > 100
    saved = json.loads((tmp_path / "crosscheck.json").read_text())
    assert saved["views"][0]["z"] == res["views"][0]["z"]
    assert (tmp_path / "crosscheck.png").stat().st_size > 10000
    n_views, nv, nu = res["projection_shape"]
    ref = np.asarray(mi.Bitmap(str(tmp_path / "reference_T.exr")))
    assert ref.shape[:2] == (n_views * nv, nu) and 0 < ref.min() < 0.95 and ref.max() <= 1


def test_a_wrong_reference_fails_the_view(tmp_path, monkeypatch):
    """The cross-check can fail: a 5 % error in the line integrals fails every view at
    256 spp (3 % fails two of the four)."""
    from mi_grg.evaluation import crosscheck as cc
    true_reference = cc.scene_reference

    def off(scan, scene):
        t, info = true_reference(scan, scene)
        return t ** 1.05, info
    monkeypatch.setattr(cc, "scene_reference", off)
    res = cc.render_scene(SCENES / "shepp_cone_volpath.xml", 256, tmp_path)
    assert not res["pass"] and all(abs(v["z"]) > 4 and not v["pass"] for v in res["views"])
    from mi_grg.cli import main
    assert main(["render", str(SCENES / "shepp_cone_volpath.xml"), "--spp", "256",
                 "--out", str(tmp_path / "cli")]) == 1


def test_samples_must_be_zero_or_one():
    from mi_grg.evaluation.crosscheck import _render_checked, load_render_scene
    _, scene = load_render_scene(SCENES / "shepp_cone_volpath.xml")
    t = _render_checked(scene, 2, 0, radiance=1.0)
    assert set(np.unique(t * 2)) <= {0.0, 1.0, 2.0}
    with pytest.raises(ValueError, match="not 0 or 1"):
        _render_checked(scene, 1, 0, radiance=2.0)    # samples 0 or 0.5: not binomial


def test_view_statistics_pass_bias_and_impossible_pixel(rng):
    spp = 64
    t = np.concatenate([rng.uniform(0.2, 0.95, (2, 16, 16)), np.ones((2, 4, 16))], 1)
    mc = rng.binomial(spp, t) / spp
    stats = view_statistics(mc, t, spp)
    assert all(v["pass"] for v in stats)
    assert stats[0]["pixels_informative"] == 256 and stats[0]["pixels"] == 320
    biased = np.clip(np.rint(mc * spp) - 3, 0, None) / spp     # 3 samples fewer escape
    biased[:, 16:] = 1.0
    assert not any(v["pass"] for v in view_statistics(biased, t, spp))
    one = mc.copy()
    one[1, 18, 3] = 1 - 1 / spp           # an absorbed sample where T = 1 (ray misses)
    s = view_statistics(one, t, spp)
    assert s[0]["pass"] and not s[1]["pass"] and s[1]["min_pixel_p_value"] == 0.0


def test_binomial_z_is_the_standard_score():
    spp = 4096
    t = np.array([0.3, 0.5, 0.8])
    mc = t + np.array([-2, 1, 3]) * np.sqrt(t * (1 - t) / spp)
    np.testing.assert_allclose(binomial_z(mc, t, spp), [-2, 1, 3], atol=0.05)
    # one absorbed sample at T = 0.999, 256 spp: mid-p 0.13 -> z = -1.1, not -8
    assert binomial_z(np.array([255 / 256]), np.array([0.999]), 256)[0] == pytest.approx(
        -1.1, abs=0.1)
    assert binomial_z(np.array([1.0]), np.array([1.0]), 16)[0] == 0.0


# ---------------------------------------------------------------- a finished run
def fake_run(tmp_path, rng, scale=0.5):
    """A run folder as gr writes it: Gaussians in the rescaled frame, metrics.json with the
    data set's geometry in file units (lengths / scale) and its test angles."""
    g, geo, _ = tiny_case(rng)
    run = tmp_path / "run"
    run.mkdir()
    g.save_npz(run / "gaussians.npz")
    file_geo = geo.scaled(1 / scale)
    test_angles = [0.1, 1.0, 2.0, 3.0, 4.0]
    (run / "metrics.json").write_text(json.dumps({
        "method": "gr", "geometry": {**file_geo.to_scanner_dict(), "n_angles": 3,
                                     "n_test_angles": 5, "scene_scale": scale},
        "data": {"scene": {"test_angles": test_angles}}}))
    return run, geo, test_angles


def test_render_run_builds_the_scene_from_the_run(tmp_path, rng):
    from mi_grg.data.scene import load_scan
    run, geo, test_angles = fake_run(tmp_path, rng)
    res = render_run(run, 32, tmp_path / "check", views=3, det=12)
    assert res["pass"], res["views"]
    scan = load_scan(tmp_path / "check" / "scene.xml")
    # the scanner is in the Gaussians' (rescaled) frame, at the asked detector size
    assert scan.geometry.DSD == pytest.approx(geo.DSD) and scan.geometry.sVoxel == geo.sVoxel
    assert scan.geometry.nDetector == (12, 12) and scan.geometry.sDetector == geo.sDetector
    np.testing.assert_allclose(scan.geometry.angles, np.asarray(test_angles)[[0, 2, 4]])
    assert res["projection_shape"] == [3, 12, 12] and res["run"] == str(run)
    assert res["angles_from"].startswith("metrics.json")


def test_cli_render_run(tmp_path, rng, capsys):
    from mi_grg.cli import main
    run, _, _ = fake_run(tmp_path, rng, scale=1.0)
    assert main(["render", "--run", str(run), "--spp", "16", "--det", "8",
                 "--out", str(tmp_path / "c")]) == 0
    out = capsys.readouterr().out
    assert "view 1" in out and "PASS" in out and (tmp_path / "c" / "crosscheck.png").is_file()


# ---------------------------------------------------------------- bad input: one line, exit 2
SENSOR = """<sensor type="ct_scanner">
  <string name="mode" value="cone"/><float name="DSD" value="7"/><float name="DSO" value="5"/>
  <string name="nDetector" value="8 8"/><string name="sDetector" value="4.2 4.2"/>
  <string name="nVoxel" value="8 8 8"/><string name="sVoxel" value="2 2 2"/>
  <integer name="views" value="1"/>{medium}</sensor>"""
PHANTOM = '<medium type="ct_phantom"><string name="phantom" value="shepp"/></medium>'
EMITTER = '<emitter type="constant"><float name="radiance" value="1"/></emitter>'
GRID = """<medium type="heterogeneous">{albedo}
  <volume type="gridvolume" name="sigma_t"><string name="filename" value="{vol}"/></volume>
</medium>"""


def _scene(tmp_path, body):
    path = tmp_path / "bad.xml"
    path.write_text(f'<scene version="3.0.0">{body}</scene>')
    return path


@pytest.mark.parametrize("body, words", [
    ('<sensor type="perspective"/>' + EMITTER + '<integrator type="volpath"/>',
     ["ct_scanner", "copy scenes/shepp_cone_volpath.xml"]),
    (SENSOR.format(medium="") + EMITTER + '<integrator type="volpath"/>',
     ["no scanned object", '<medium type="ct_phantom">']),
    (SENSOR.format(medium=PHANTOM) + EMITTER + '<integrator type="path"/>',
     ["integrator 'path'", '<integrator type="volpath"/>']),
    (SENSOR.format(medium=PHANTOM) + EMITTER, ["no integrator", '<integrator type="volpath"/>']),
    (SENSOR.format(medium=PHANTOM) + '<integrator type="volpath"/>',
     ['<emitter type="constant">']),
    (SENSOR.format(medium=GRID.format(albedo="", vol="{vol}")) + EMITTER +
     '<integrator type="volpath"/>', ["pure absorber", 'name="albedo" value="0"']),
    (SENSOR.format(medium=GRID.format(albedo='<float name="albedo" value="0"/>', vol="{vol}"))
     + EMITTER + '<integrator type="volpath"/>', ["has_spectral_extinction"]),
])
def test_bad_scene_is_one_line_exit_2(tmp_path, capsys, body, words):
    from mi_grg.cli import main
    body = body.replace("{vol}", str(SCENES / "shepp_grid32.vol"))
    assert main(["render", str(_scene(tmp_path, body)), "--spp", "4",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("mi-grg render: error:"), err
    for w in words:
        assert w in err, (w, err)


def test_run_without_gaussians_is_one_line_exit_2(tmp_path, rng, capsys):
    from mi_grg.cli import main
    run, _, _ = fake_run(tmp_path, rng)
    (run / "gaussians.npz").unlink()
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no gaussians.npz" in err
    assert "mi-grg reconstruct DATA --method gr" in err and "--resume" not in err
    (run / "checkpoint.npz").write_bytes(b"")          # an unfinished run
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "o")]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["render", "--run", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_scene_and_run_are_exclusive(tmp_path, capsys):
    from mi_grg.cli import main
    assert main(["render", "--out", str(tmp_path)]) == 2
    assert main(["render", str(SCENES / "shepp_cone_volpath.xml"), "--det", "8",
                 "--out", str(tmp_path)]) == 2
    assert "only apply with --run" in capsys.readouterr().err


def test_render_run_takes_test_angles_from_the_data_set(tmp_path, rng):
    from mi_grg.cli import main
    from mi_grg.data.scene import load_scan
    from mi_grg.data.simulate import default_test_angles
    run, _, _ = fake_run(tmp_path, rng)
    main(["simulate", "--phantom", "shepp", "--n", "8", "--det", "8", "--views", "2",
          "--test-views", "3", "--no-noise", "--out", str(tmp_path / "data")])
    res = render_run(run, 8, tmp_path / "check", views=2, det=8, data=tmp_path / "data")
    assert res["angles_from"].startswith("data set")
    np.testing.assert_allclose(load_scan(tmp_path / "check" / "scene.xml").geometry.angles,
                               default_test_angles(3)[[0, 2]])


def test_render_run_of_a_per_view_run_uses_each_test_views_frame(tmp_path, rng):
    """A run on a wobbling orbit: the cross-check's sensors are its data set's test views,
    each in its own frame (rows rescaled to the training frame, pixels resized), volpath
    agrees with the projector there, and the nominal circle's transmittance would not."""
    import mi_grg as m
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.orbits import wobbling
    from mi_grg.data.scene import load_scan
    from mi_grg.data.simulate import simulate_case
    from mi_grg.evaluation.crosscheck import view_statistics
    from mi_grg.core.projector import project
    g, geo, _ = tiny_case(rng)
    scale = 0.5
    test = np.array([0.1, 1.0, 2.0, 3.0, 4.0])
    # two angles outside the run's: the picked test views are mid-wobble, not at its ends
    allv = wobbling(geo.scaled(1 / scale).with_angles(np.concatenate([[-0.5], geo.angles,
                                                                      test, [5.9]])),
                    height=1.2, roll_deg=15.0, dsd=0.05)
    case = simulate_case("shepp", allv.with_angles(geo.angles), test, NoiseModel(), seed=1)
    m.save_case(case, tmp_path / "data")
    run = tmp_path / "run"
    run.mkdir()
    g.save_npz(run / "gaussians.npz")
    (run / "metrics.json").write_text(json.dumps({
        "method": "gr", "geometry": {**allv.circular().to_scanner_dict(), "n_angles": 3,
                                     "n_test_angles": 5, "scene_scale": scale,
                                     "per_view": True}}))
    with pytest.raises(ValueError, match="per-view: pass --data"):
        render_run(run, 8, tmp_path / "nodata", views=3, det=12)
    res = render_run(run, 256, tmp_path / "check", views=3, det=12, data=tmp_path / "data")
    assert res["pass"], res["views"]
    assert res["test_view_indices"] == [0, 2, 4]
    got = load_scan(tmp_path / "check" / "scene.xml").geometry
    # the data set's rows of test views 0, 2, 4, by hand: lengths x scale, pixel steps x 16/12
    want = allv.view_vectors(test[[0, 2, 4]])
    want *= scale
    want[:, 6:] *= 16 / 12
    np.testing.assert_allclose(got.view_vectors(), want, rtol=1e-12, atol=1e-12)
    mc = np.asarray(mi.Bitmap(str(tmp_path / "check" / "volpath_T.exr")), np.float64)
    circle = np.exp(-np.asarray(project(g, got.circular()), np.float64))
    st = view_statistics(mc.reshape(circle.shape), circle, 256)
    assert not any(v["pass"] for v in st)
