"""`mi-grg` end to end on a tiny case: simulate -> reconstruct, the data set's scene XML,
and the flags that a scene file states itself (errors together with --scene)."""
import json
import re
from pathlib import Path

import numpy as np
import pytest

from mi_grg.cli import SCENE_XML, main
from mi_grg.data.scene import load_scan

SCENES = Path(__file__).resolve().parent.parent / "scenes"
TINY = ["--n", "16", "--det", "24", "--views", "6", "--test-views", "2"]


@pytest.fixture(scope="module")
def shepp_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "shepp"
    assert main(["simulate", "--phantom", "shepp", *TINY, "--out", str(out)]) == 0
    return out


def test_simulate_then_reconstruct_fdk(shepp_data, tmp_path):
    out = tmp_path / "fdk"
    assert main(["reconstruct", str(shepp_data), "--method", "fdk", "--out", str(out)]) == 0
    gt = np.load(shepp_data / "vol_gt.npy")
    pred = np.load(out / "vol_pred.npy")
    assert gt.shape == (16, 16, 16) and pred.shape == gt.shape
    assert (out / "slices.png").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "fdk" and np.isfinite(metrics["psnr_3d"])
    # the scanner geometry is echoed as meta_data.json states it
    scanner = json.loads((shepp_data / "meta_data.json").read_text())["scanner"]
    geo = metrics["geometry"]
    for k in ("mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel",
              "offOrigin", "offDetector"):
        assert geo[k] == scanner[k], k
    assert geo["n_angles"] == 6 and geo["n_test_angles"] == 2 and geo["scene_scale"] == 1.0
    assert metrics["clamped_negatives"] == {}      # simulate clips its noise itself
    # what was simulated, as the scene states it
    scene = metrics["data"]["scene"]
    assert scene["object"] == {"type": "ct_phantom", "phantom": "shepp"}
    assert scene["noise"] == {"model": "poisson+gaussian", "I0": 1e4, "electronic_std": 10.0,
                           "seed": 0, "clip_negative": True}
    assert scene["integrator"] == {} and scene["other"] == []
    assert metrics["data"]["scene_xml"] == SCENE_XML


def test_default_simulate_writes_its_scene_xml(shepp_data):
    scan = load_scan(shepp_data / SCENE_XML)
    g = scan.geometry
    assert (g.mode, g.nVoxel, g.nDetector, g.n_views) == ("cone", (16,) * 3, (24, 24), 6)
    meta = json.loads((shepp_data / "meta_data.json").read_text())
    np.testing.assert_array_equal(g.angles, [e["angle"] for e in meta["proj_train"]])
    np.testing.assert_array_equal(scan.test_angles, [e["angle"] for e in meta["proj_test"]])
    assert scan.noise == {"model": "poisson+gaussian", "I0": 1e4, "electronic_std": 10.0,
                           "seed": 0, "clip_negative": True}
    assert scan.object == {"type": "ct_phantom", "phantom": "shepp"}
    assert scan.integrator == {} and scan.other == []


def test_scene_xml_of_a_data_set_reproduces_it(tmp_path):
    """Every flag of the default path lands in scene.xml: --scene of it gives the same data."""
    first, again = tmp_path / "first", tmp_path / "again"
    main(["simulate", "--phantom", "needles", "--seed", "5", "--mode", "parallel",
          "--I0", "3000", "--electronic-std", "4", *TINY, "--out", str(first)])
    scan = load_scan(first / SCENE_XML)
    assert scan.geometry.mode == "parallel"
    assert scan.noise == {"model": "poisson+gaussian", "I0": 3000.0, "electronic_std": 4.0,
                          "seed": 5, "clip_negative": True}
    assert scan.object == {"type": "ct_phantom", "phantom": "needles", "seed": 5}
    main(["simulate", "--scene", str(first / SCENE_XML), "--out", str(again)])
    for rel in ("vol_gt.npy", "proj_train/proj_train_0003.npy", "proj_test/proj_test_0001.npy"):
        np.testing.assert_array_equal(np.load(again / rel), np.load(first / rel), err_msg=rel)
    assert (again / SCENE_XML).read_text() == (first / SCENE_XML).read_text()


def test_scene_path_records_overrides_and_seed(tmp_path):
    scene = tmp_path / "tiny.xml"
    scene.write_text(f"""<scene version="3.0.0">
    <sensor type="ct_scanner">
        <string name="mode" value="cone"/>
        <float name="DSD" value="7"/> <float name="DSO" value="5"/>
        <string name="nDetector" value="24 24"/> <string name="sDetector" value="4.2 4.2"/>
        <string name="nVoxel" value="16 16 16"/> <string name="sVoxel" value="2 2 2"/>
        <integer name="views" value="9"/>
        <medium type="ct_phantom">
            <string name="phantom" value="shells"/> <integer name="seed" value="3"/>
        </medium>
    </sensor>
</scene>""")
    out = tmp_path / "data"
    main(["simulate", "--scene", str(scene), "--views", "4", "--out", str(out)])
    meta = json.loads((out / "meta_data.json").read_text())
    assert len(meta["proj_train"]) == 4 and meta["proj_test"] == []
    assert meta["mi_grg"]["seed"] == 3 and meta["mi_grg"]["noise"] is None
    assert meta["mi_grg"]["scene"]["scene"] == str(scene)
    written = load_scan(out / SCENE_XML)          # the effective scan, override included
    assert written.geometry.n_views == 4 and written.noise is None
    assert written.object == {"type": "ct_phantom", "phantom": "shells", "seed": 3}


@pytest.mark.parametrize("flags, names", [
    (["--phantom", "needles"], ["--phantom"]),
    (["--phantom", "shepp"], ["--phantom"]),          # the scene's own value: still an error
    (["--no-noise"], ["--no-noise"]),
    (["--I0", "1e4"], ["--I0"]),
    (["--electronic-std", "3"], ["--electronic-std"]),
    (["--seed", "0"], ["--seed"]),                     # a default value, given explicitly
    (["--n", "16"], ["--n"]),
    (["--det", "24", "--mode", "cone"], ["--det", "--mode"]),
])
def test_scene_refuses_flags_that_the_scene_states(tmp_path, flags, names, capsys):
    out = tmp_path / "data"
    assert main(["simulate", "--scene", str(SCENES / "shepp_cone.xml"), *flags,
                 "--out", str(out)]) == 2
    msg = capsys.readouterr().err
    assert msg.startswith("mi-grg simulate: error: " + ", ".join(names) +
                          " cannot be combined with --scene") and msg.count("\n") == 1
    assert "Edit the scene file instead" in msg
    assert not out.exists()


def test_scene_with_an_unused_integrator_is_refused(tmp_path, capsys):
    out = tmp_path / "data"
    assert main(["simulate", "--scene", str(SCENES / "shepp_cone_volpath.xml"),
                 "--out", str(out)]) == 2
    msg = capsys.readouterr().err
    assert re.search(r'integrator type="volpath".*emitter type="constant".*mi-grg render', msg)
    assert "shepp_cone_volpath.xml" in msg
    assert not out.exists()


def test_scene_without_a_phantom_is_refused(tmp_path, capsys):
    scene = tmp_path / "gauss.xml"
    text = (SCENES / "shepp_cone.xml").read_text()
    start, end = text.index("<medium"), text.index("</medium>") + len("</medium>")
    scene.write_text(text[:start] + text[end:])
    assert main(["simulate", "--scene", str(scene), "--out", str(tmp_path / "data")]) == 2
    assert re.search(r'gauss\.xml: .*ct_phantom.*got no medium', capsys.readouterr().err)


def test_no_noise_contradicts_noise_flags(tmp_path, capsys):
    assert main(["simulate", "--no-noise", "--I0", "100", "--electronic-std", "1", *TINY,
                 "--out", str(tmp_path / "data")]) == 2
    assert re.search("--I0 and --electronic-std set the noise model.*--no-noise",
                     capsys.readouterr().err)


def test_shepp_noise_seed_is_stated_and_reproduced(tmp_path):
    """Shepp-Logan takes no phantom seed, but --seed still seeds the noise: scene.xml says
    so (noise_seed), and --scene of it reproduces the noisy views; another seed differs."""
    small = ["--n", "8", "--det", "12", "--views", "3", "--test-views", "0"]
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    main(["simulate", "--seed", "2", *small, "--out", str(a)])
    main(["simulate", "--scene", str(a / SCENE_XML), "--out", str(b)])
    main(["simulate", "--seed", "3", *small, "--out", str(c)])
    scan = load_scan(a / SCENE_XML)
    assert scan.noise["seed"] == 2 and "seed" not in scan.object
    rel = "proj_train/proj_train_0001.npy"
    np.testing.assert_array_equal(np.load(b / rel), np.load(a / rel))
    assert not np.array_equal(np.load(c / rel), np.load(a / rel))


def _scene_with(tmp_path, extra: str):
    text = (SCENES / "shepp_cone.xml").read_text()
    anchor = text.index('<float   name="electronic_std"')
    scene = tmp_path / "scene.xml"
    scene.write_text(text[:anchor] + extra + "\n        " + text[anchor:])
    return scene


def test_clip_negative_false_keeps_negative_noisy_values(tmp_path):
    """clip_negative in the scene is what runs: with false, noise on empty detector
    pixels leaves negative line integrals; the default (true) clips them to 0."""
    scene = _scene_with(tmp_path, '<boolean name="clip_negative" value="false"/>')
    out, clipped = tmp_path / "raw", tmp_path / "clipped"
    main(["simulate", "--scene", str(scene), "--views", "3", "--test-views", "0",
          "--out", str(out)])
    main(["simulate", "--scene", str(SCENES / "shepp_cone.xml"), "--views", "3",
          "--test-views", "0", "--out", str(clipped)])
    raw = np.load(out / "proj_train/proj_train_0000.npy")
    assert raw.min() < 0
    np.testing.assert_array_equal(np.maximum(raw, 0),
                                  np.load(clipped / "proj_train/proj_train_0000.npy"))
    assert load_scan(out / SCENE_XML).noise["clip_negative"] is False
    meta = json.loads((out / "meta_data.json").read_text())
    assert meta["mi_grg"]["noise"]["clip_negative"] is False


@pytest.mark.parametrize("extra, match", [
    ('<integer name="noise_seed" value="-1"/>', "noise_seed must be an integer >= 0"),
    ('<string name="clip_negative" value="maybe"/>', "clip_negative must be a boolean"),
])
def test_bad_noise_fields_are_named(tmp_path, extra, match):
    with pytest.raises(Exception, match=match):
        load_scan(_scene_with(tmp_path, extra))


def test_reconstruct_option_errors_are_one_line(shepp_data, tmp_path, capsys):
    """An option a method does not take is named, without a traceback (exit code 2)."""
    assert main(["reconstruct", str(shepp_data), "--method", "fdk", "--resume",
                 "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "does not take option(s) ['resume']" in err and "Traceback" not in err
    assert main(["reconstruct", str(shepp_data), "--method", "gr", "--option",
                 "lamda_lap=1", "--out", str(tmp_path / "b")]) == 2
    assert "did you mean 'lambda_lap'" in capsys.readouterr().err


def test_reconstruct_resume_flag_continues_a_gr_run(shepp_data, tmp_path):
    out = tmp_path / "gr"
    opts = ["--option", "iterations=20", "--option", "n_points=300", "--option",
            "checkpoint_every=10", "--option", "progress=false",
            "--option", "holdout_every=4"]     # two of the 8 views decide
    assert main(["reconstruct", str(shepp_data), "--method", "gr", *opts,
                 "--out", str(out)]) == 0
    assert main(["reconstruct", str(shepp_data), "--method", "gr", *opts, "--resume",
                 "--out", str(out)]) == 0
    info = json.loads((out / "metrics.json").read_text())["method_info"]
    assert info["init"] == {"resumed_from": 20} and info["iterations_run"] == 20
