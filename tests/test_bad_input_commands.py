"""Bad input for `mi-grg render`, `report`, `experiment`, memory and the error paths
(tests/test_bad_input.py has import, reconstruct and simulate): each broken input of the
tables below ends in exit status 2 and one line on stderr naming the culprit, without a
Python traceback, and every input and earlier output is byte-identical afterwards (the
whole workspace is hashed before and after). Then the paths that succeed (a run that does
not read back is named, an earlier render is replaced whole), the disk-full message, the
Dask instructions, and the fuzzing of every input file kind (scripts/fuzz_inputs.py)."""
from __future__ import annotations

import importlib.util
import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_grg.cli import MAX_MESSAGE, main

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("fuzz_inputs", ROOT / "scripts" / "fuzz_inputs.py")
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """The fuzzer's workspace: data/, run/ (fdk), gr/ (a gr run with its checkpoint),
    render/ (of gr), scan/ flats/ darks/ prev/ (FIPS scan, its import), naf.pickle,
    suite.json, results/ and report/, config.xml, scene.xml and sim/."""
    return fuzz.build(tmp_path_factory.mktemp("commands") / "w")


def run_cli(argv, capsys) -> tuple:
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    captured = capsys.readouterr()
    return rc, captured.err.strip(), captured.out


# ---------------------------------------------------------------- breaking the inputs
def _other_folder(r):
    (r / "other").mkdir()
    (r / "other" / "thesis.tex").write_text("months of work")


def _a_file(r):
    (r / "notes.txt").write_text("not a report")


def _foreign_image(r):
    (r / "report" / "img" / "results" / "plan.txt").write_text("not an image")


def _garbage(name):
    def f(r):
        (r / name).write_bytes(b"garbage\n")
    return f


def _truncated(name):
    def f(r):
        (r / name).write_bytes((r / name).read_bytes()[:3000])
    return f


def _meta(r, **changes):
    path = r / "data" / "meta_data.json"
    meta = json.loads(path.read_text())
    for key, value in changes.items():
        if key == "nVoxel":
            meta["scanner"]["nVoxel"] = value
            meta["scanner"].pop("dVoxel", None)
            meta.pop("vol", None)
        elif key == "file_path":
            meta["proj_train"][0]["file_path"] = value
        else:
            meta[key] = value
    path.write_text(json.dumps(meta))


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _complex_gaussians(r):
    with np.load(r / "gr" / "gaussians.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["positions"] = arrays["positions"].astype(np.complex64)
    np.savez(r / "gr" / "gaussians.npz", **arrays)


def _config_value(name, value):
    def f(r):
        text = (r / "config.xml").read_text()
        start = text.index(f'name="{name}" value="') + len(f'name="{name}" value="')
        (r / "config.xml").write_text(text[:start] + value + text[text.index('"', start):])
    return f


def _zero_truth(r):
    np.save(r / "data" / "vol_gt.npy", np.zeros_like(np.load(r / "data" / "vol_gt.npy")))


def _outside(r):
    shutil.copy(r / "data" / "proj_train" / "proj_train_0000.npy", r / "outside.npy")


def _scene_field(field, value):
    def f(r):
        text = (r / "scene.xml").read_text()
        start = text.index(f'name="{field}" value="') + len(f'name="{field}" value="')
        (r / "scene.xml").write_text(text[:start] + value + text[text.index('"', start):])
    return f


def _unknown_scene_key(r):
    text = (r / "scene.xml").read_text()
    (r / "scene.xml").write_text(text.replace(
        '<integer name="views"', '<integer name="bogus_key" value="1"/><integer name="views"'))


def _many_shapes(n):
    def f(r):
        text = (r / "scene.xml").read_text()
        (r / "scene.xml").write_text(text.replace("</scene>", '<shape type="sphere"/>\n' * n
                                                  + "</scene>"))
    return f


def _long_attribute(n):
    def f(r):
        (r / "config.xml").write_text(f'<training method="gr">\n<integer name="{"x" * n}" '
                                      'value="1"/>\n</training>\n')
    return f


def _checkpoint(edit):
    def f(r):
        path = r / "gr" / "checkpoint.npz"
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        edit(arrays)
        np.savez(path, **arrays)
    return f


def _without_config(arrays):
    meta = json.loads(bytes(arrays["meta"]).decode())
    del meta["config"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)


def _nan_density(arrays):
    arrays["raw__raw_densities"] = np.full_like(arrays["raw__raw_densities"], np.nan)


def _empty_checkpoint(r):
    (r / "gr" / "checkpoint.npz").write_bytes(b"")


def _deep_pickle(r):
    n, key = 200_000, b"DSD"      # {"DSD": [[[...]]]} 200,000 lists deep, in opcodes
    (r / "deep.pickle").write_bytes(b"\x80\x04}\x8c" + bytes([len(key)]) + key + b"]" * n
                                    + b"a" * (n - 1) + b"s.")


def _deep_meta(r):
    (r / "data" / "meta_data.json").write_text("[" * 200_000 + "]" * 200_000)


def _suite(edit):
    def f(r):
        (r / "suite.json").write_text(edit((r / "suite.json").read_text()))
    return f


def _int_projection(r):
    p = r / "data" / "proj_train" / "proj_train_0001.npy"
    np.save(p, (np.load(p) * 1000).astype(np.int64))


RENDER = ["--run", "{r}/gr", "--spp", "2", "--det", "8", "--views", "1"]
GR_RESUME = ["{r}/data", *fuzz.GR, "--resume", "--out", "{r}/gr"]
FDK = ["{r}/data", "--method", "fdk", "--out", "{r}/run"]

# name: (command and arguments, what to break first, what the one-line message must name)
CASES = {
    # render and report protect what they write over
    "render into a data set": (["render", *RENDER, "--out", "{r}/data"], None,
                               ["--out", "not an earlier mi-grg render output"]),
    "render --spp 0 over an earlier render": (
        ["render", "--run", "{r}/gr", "--spp", "0", "--out", "{r}/render"], None, ["--spp 0"]),
    "render --det 100000": (["render", "--run", "{r}/gr", "--det", "100000", "--out",
                             "{r}/new"], None, ["--det 100000"]),
    "render into a folder of other files": (["render", *RENDER, "--out", "{r}/other"],
                                            _other_folder, ["--out", "crosscheck.json"]),
    "render into the run": (["render", *RENDER, "--out", "{r}/gr/check"], None,
                            ["--out", "lies inside the input"]),
    "render --preview into a data set": (["render", "--run", "{r}/gr", "--preview", "--out",
                                          "{r}/data"], None,
                                         ["--out", "not an earlier preview"]),
    "simulate over an imported scan": (["simulate", "--n", "8", "--det", "8", "--views", "2",
                                        "--out", "{r}/prev"], None,
                                       ["--out", "not a simulated data set", "import.json"]),
    "report over the runner's runs.json": (
        ["report", "--out", "{r}/results", "--report", "{r}/results/table1/runs.json"], None,
        ["--report", "lies inside the input", "table1"]),
    "report of a folder without runs": (["report", "--out", "{r}/other", "--report",
                                         "{r}/rep/results.md"], _other_folder,
                                        ["--out", "holds no runs"]),
    "report over a file that is no report": (
        ["report", "--out", "{r}/results", "--report", "{r}/notes.txt"], _a_file,
        ["--report", "not an earlier report"]),
    "a record inside the results": (
        ["report", "--out", "{r}/results", "--report", "{r}/rep/results.md", "--record",
         "{r}/results/kept"], None, ["--record", "lies inside the input"]),
    "a record in a folder of other files": (
        ["report", "--out", "{r}/results", "--report", "{r}/rep/results.md", "--record",
         "{r}/other"], _other_folder, ["--record", "thesis.tex", "no record wrote"]),
    "a report inside its record": (
        ["report", "--out", "{r}/results", "--report", "{r}/kept/results.md", "--record",
         "{r}/kept"], None, ["--report", "lies inside the input"]),
    "report beside images it did not write": (
        ["report", "--out", "{r}/results", "--report", "{r}/report/results.md"],
        _foreign_image, ["--report", "plan.txt"]),
    # memory is bounded before allocation
    "reconstruct fdk at 1500^3": (["reconstruct", *FDK], lambda r: _meta(r, nVoxel=[1500] * 3),
                                  ["nVoxel", "1500 x 1500 x 1500", "one array"]),
    "reconstruct sart at 1500^3": (
        ["reconstruct", "{r}/data", "--method", "sart", "--out", "{r}/run"],
        lambda r: _meta(r, nVoxel=[1500] * 3), ["nVoxel", "one array"]),
    "reconstruct fdk at 2000^3": (["reconstruct", *FDK], lambda r: _meta(r, nVoxel=[2000] * 3),
                                  ["2000 x 2000 x 2000", "one array"]),
    "reconstruct sart at 100000^3": (
        ["reconstruct", "{r}/data", "--method", "sart", "--out", "{r}/run"],
        lambda r: _meta(r, nVoxel=[100000] * 3), ["100000 x 100000 x 100000", "one array"]),
    "a case whose projections cannot fit": (
        ["reconstruct", *FDK], lambda r: _meta(r, scanner={
            **{k: v for k, v in json.loads((r / "data" / "meta_data.json").read_text())[
                "scanner"].items() if k != "dDetector"}, "nDetector": [100000, 100000]}),
        ["meta_data.json", "projections 8 x 100000 x 100000", "one array"]),
    "reconstruct gr above --max-memory": (
        ["reconstruct", "{r}/data", *fuzz.GR, "--max-memory", "0.01", "--out", "{r}/gr"], None,
        ["GiB", "--max-memory"]),
    "simulate --n 2000": (["simulate", "--n", "2000", "--det", "8", "--views", "2",
                           "--test-views", "0", "--out", "{r}/new"], None,
                          ["2000 x 2000 x 2000", "one array"]),
    "simulate above --max-memory": (["simulate", "--n", "400", "--det", "8", "--views", "2",
                                     "--max-memory", "0.05", "--out", "{r}/new"], None,
                                    ["--max-memory", "GiB"]),
    "render above --max-memory": (["render", *RENDER, "--max-memory", "1e-5", "--out",
                                   "{r}/new"], None, ["--max-memory", "film"]),
    "a scene of 400,000 shapes": (["simulate", "--scene", "{r}/scene.xml", "--out", "{r}/new"],
                                  _many_shapes(400_000), ["scene.xml", "MiB"]),
    "a scene of 20,000 elements": (["simulate", "--scene", "{r}/scene.xml", "--out",
                                    "{r}/new"], _many_shapes(20_000),
                                   ["scene.xml", "more than 10000 elements"]),
    "a config of 50 MB": (["reconstruct", "{r}/data", "--method", "gr", "--config",
                           "{r}/config.xml", "--out", "{r}/new"], _long_attribute(50_000_000),
                          ["config.xml", "MiB"]),
    "a config attribute of 2 MB": (["reconstruct", "{r}/data", "--method", "gr", "--config",
                                    "{r}/config.xml", "--out", "{r}/new"],
                                   _long_attribute(2_000_000), ["config.xml", "characters"]),
    "an option name of 100,000 characters": (
        ["reconstruct", *FDK[:3], "--option", "y" * 100_000 + "=1", "--out", "{r}/run"], None,
        ["does not take option", " ..."]),
    # no traceback on any user error
    "simulate --scene with an unknown key": (
        ["simulate", "--scene", "{r}/scene.xml", "--out", "{r}/new"], _unknown_scene_key,
        ["scene.xml", "bogus_key"]),
    "simulate --scene with DSO > DSD": (
        ["simulate", "--scene", "{r}/scene.xml", "--out", "{r}/new"], _scene_field("DSO", "9"),
        ["scene.xml", "DSO (source-origin, 9.0) must be < DSD"]),
    "simulate --scene with a negative sVoxel": (
        ["simulate", "--scene", "{r}/scene.xml", "--out", "{r}/new"],
        _scene_field("sVoxel", "-2 2 2"), ["scene.xml", "sVoxel must be > 0"]),
    "render a run with a bad gaussians.npz": (["render", *RENDER, "--out", "{r}/new"],
                                              _garbage("gr/gaussians.npz"),
                                              ["gaussians.npz", "not an .npz archive"]),
    "render a run whose metrics.json has a bad geometry": (
        ["render", *RENDER, "--out", "{r}/new"], lambda r: _edit_json(
            r / "gr" / "metrics.json", lambda m: m["geometry"].update(mode=0.5)),
        ["gr/metrics.json", "mode must be one of"]),
    "render a run whose Gaussians are complex": (
        ["render", *RENDER, "--out", "{r}/new"], _complex_gaussians,
        ["gaussians.npz", "positions must hold real numbers"]),
    "render a run with a truncated gaussians.npz": (
        ["render", *RENDER, "--out", "{r}/new"], _truncated("gr/gaussians.npz"),
        ["gaussians.npz", "truncated"]),
    "a checkpoint with an array of the wrong shape": (
        ["reconstruct", *GR_RESUME],
        _checkpoint(lambda a: a.update(raw__positions=a["raw__positions"][:, :2])),
        ["checkpoint.npz", "raw__positions has shape"]),
    "a checkpoint whose meta lacks the config": (
        ["reconstruct", *GR_RESUME], _checkpoint(_without_config),
        ["checkpoint.npz", "'config'"]),
    "a checkpoint whose graph positions are flat": (
        ["reconstruct", *GR_RESUME],
        _checkpoint(lambda a: a.update(graph_positions=a["graph_positions"].ravel())),
        ["checkpoint.npz", "graph_positions", "[M, 3]"]),
    "a checkpoint without one of Adam's moments": (
        ["reconstruct", *GR_RESUME], _checkpoint(lambda a: a.pop("adam_v__raw_densities")),
        ["checkpoint.npz", "adam_steps", "raw_densities"]),
    "an empty checkpoint": (["reconstruct", *GR_RESUME], _empty_checkpoint,
                            ["checkpoint.npz", "truncated?"]),
    "a checkpoint of NaN": (["reconstruct", *GR_RESUME], _checkpoint(_nan_density),
                            ["checkpoint.npz", "raw__raw_densities", "NaN"]),
    "a NAF pickle 200,000 deep": (["import", "{r}/deep.pickle", "--out", "{r}/new"],
                                  _deep_pickle, ["deep.pickle", "nested too deeply"]),
    "a meta_data.json 200,000 deep": (["reconstruct", *FDK], _deep_meta,
                                      ["meta_data.json", "nested too deeply"]),
    # nothing silent
    "a suite with a misspelt key": (
        ["experiment", "table1", "--suite", "{r}/suite.json", "--out", "{r}/results",
         "--dry-run"], _suite(lambda t: t.replace('"method_options"', '"method_option"')),
        ["'method_option'", "did you mean 'method_options'"]),
    "a suite with a misspelt option": (
        ["experiment", "table1", "--suite", "{r}/suite.json", "--out", "{r}/results",
         "--dry-run"], _suite(lambda t: t.replace('"n_iter"', '"n_itr"')),
        ["method_options.sart", "'n_itr'", "did you mean 'n_iter'"]),
    "a suite whose methods are no names": (
        ["experiment", "table1", "--suite", "{r}/suite.json", "--out", "{r}/results",
         "--dry-run"], lambda r: _edit_json(r / "suite.json", lambda s: s["experiments"][
             "table1"].update(methods=[1e308, "sart"])),
        ["experiments.table1.methods must be a list of method names"]),
    "a --methods name no run uses": (
        ["experiment", "table1", "--suite", "{r}/suite.json", "--out", "{r}/results",
         "--methods", "sart,fkd", "--dry-run"], None, ["--methods fkd", "fdk", "sart"]),
    "--jobs 0": (
        ["experiment", "table1", "--suite", "{r}/suite.json", "--out", "{r}/results",
         "--jobs", "0"], None, ["jobs must be >= 1, got 0"]),
    "a config value out of range": (
        ["reconstruct", "{r}/data", "--method", "gr", "--config", "{r}/config.xml", "--out",
         "{r}/new"], _config_value("holdout_until", "inf"), ["config.xml", "holdout_until"]),
    "a ground truth of zeros": (["reconstruct", *FDK], _zero_truth,
                                ["ground truth (vol_gt)", "no voxel above 0"]),
    "integer projections": (["reconstruct", *FDK], _int_projection,
                            ["proj_train_0001.npy", "int64", "mi-grg import"]),
    "a file_path that is absolute": (
        ["reconstruct", *FDK], lambda r: (_outside(r), _meta(r, file_path=str(r / "outside.npy"))),
        ["proj_train[0].file_path", "outside the case folder"]),
    "a file_path up and out": (
        ["reconstruct", *FDK], lambda r: (_outside(r), _meta(r, file_path="../outside.npy")),
        ["proj_train[0].file_path", "outside the case folder"]),
    "a vol outside the case": (["reconstruct", *FDK],
                               lambda r: (_outside(r), _meta(r, vol="../../outside.npy")),
                               ["vol", "outside the case folder"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_refused(name, root, capsys, tree_hash):
    argv, breaks, culprits = CASES[name]
    if breaks:
        breaks(root)
    before = tree_hash(root)
    rc, err, _ = run_cli([a.replace("{r}", str(root)) for a in argv], capsys)
    assert rc == 2, (rc, err[:500])
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err and 'File "' not in err, err[:2000]
    assert lines[0].startswith(f"mi-grg {argv[0]}: error: ") and len(lines[0]) <= \
        len(f"mi-grg {argv[0]}: error: ") + MAX_MESSAGE, lines[0][:500]
    for c in culprits:
        assert c in err, (c, err)
    assert tree_hash(root) == before   # inputs and earlier outputs untouched, no temporaries


def test_an_error_is_not_blamed_on_a_text_option(root, capsys, tree_hash):
    """A text --option (refine=none) is named only when the error is about it: here the
    memory limit is."""
    before = tree_hash(root)
    rc, err, _ = run_cli(["reconstruct", str(root / "data"), *fuzz.GR, "--max-memory",
                          "0.01", "--out", str(root / "new")], capsys)
    assert rc == 2 and "--max-memory" in err and "passed as text" not in err, err
    assert tree_hash(root) == before


def test_variant_without_a_gpu(root, capsys, tree_hash):
    import mi_grg
    if "cuda_ad_mono" in mi_grg.available_variants():
        pytest.skip("this machine has a GPU")
    before = tree_hash(root)
    rc, err, _ = run_cli(["--variant", "cuda_ad_mono", "reconstruct", *(
        a.replace("{r}", str(root)) for a in FDK)], capsys)
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "--variant cuda_ad_mono" in err and "GPU" in err and "Traceback" not in err
    assert tree_hash(root) == before


def test_no_traceback_in_a_real_process(root, tree_hash):
    """The installed entry point: a bad MI_GRG_VARIANT (raised while the package is
    imported, before the command's own error handling) and a plugin's error that Mitsuba
    flattens into its own message each end in one line."""
    env = dict(os.environ, MI_GRG_VARIANT="bogus")
    res = subprocess.run([sys.executable, "-m", "mi_grg.cli", "--help"], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode != 0 and res.stderr.strip().splitlines() == [
        "mi-grg: error: MI_GRG_VARIANT='bogus': variant must be one of ('llvm_ad_mono', "
        "'cuda_ad_mono'), got 'bogus'"], res.stderr
    _scene_field("DSO", "9")(root)
    before = tree_hash(root)
    res = subprocess.run([sys.executable, "-m", "mi_grg.cli", "simulate", "--scene",
                          str(root / "scene.xml"), "--out", str(root / "new")],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "Traceback" not in res.stderr and 'File "' not in res.stderr
    assert tree_hash(root) == before


def test_one_error_line_without_traceback():
    """What Mitsuba makes of a plugin's error (its traceback flattened into the message)
    reaches the terminal as the error itself, from the scene reader and from the CLI's one
    error printer alike; a long message is cut."""
    from mi_grg.cli import one_line
    from mi_grg.data.inputs import without_traceback
    flat = ('s.xml: [parser.cpp:1718] failed to instantiate sensor plugin of type '
            '"ct_scanner": Traceback (most recent call last): File "/x/ct_scanner.py", line '
            '188, in <lambda> File "<string>", line 13, in __init__ GeometryError: DSO must '
            'be < DSD')
    want = ('s.xml: [parser.cpp:1718] failed to instantiate sensor plugin of type '
            '"ct_scanner": GeometryError: DSO must be < DSD')
    assert without_traceback(flat) == want and one_line(flat) == want
    full = 'x: Traceback (most recent call last):\n  File "a.py", line 3, in f\n    g()\nValueError: bad'
    assert one_line(full) == "x: ValueError: bad"
    assert len(one_line("z" * 10_000)) == MAX_MESSAGE and one_line("z" * 10_000).endswith(" ...")


def test_scene_errors_name_the_error_not_the_traceback(root):
    from mi_grg.data.scene import ScanError, load_scan
    _scene_field("DSO", "9")(root)
    with pytest.raises(ScanError) as e:
        load_scan(root / "scene.xml")
    assert "Traceback" not in str(e.value) and 'File "' not in str(e.value)
    assert "GeometryError: DSO (source-origin, 9.0) must be < DSD" in str(e.value)


# ---------------------------------------------------------------- what succeeds
def test_a_render_replaces_an_earlier_one_whole(root, capsys):
    """Not a merge: a file of the earlier render that the new one lacks is gone, and
    crosscheck.json names the folder, not the temporary it was built in."""
    (root / "render" / "stale.png").write_bytes(b"old")
    rc, err, _ = run_cli(["render", *(a.replace("{r}", str(root)) for a in RENDER), "--out",
                          str(root / "render")], capsys)
    assert rc in (0, 1), err
    assert not (root / "render" / "stale.png").exists()
    res = json.loads((root / "render" / "crosscheck.json").read_text())
    assert res["scene"] == str(root / "render" / "scene.xml")
    assert res["files"] and all(Path(f).parent == root / "render" for f in res["files"])
    assert ".render-" not in json.dumps(res) and ".." not in res["gaussians"]
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


def _results_with(root, damage) -> tuple:
    run = root / "results" / "table1" / "shepp" / "fdk"
    damage(run)
    return run


@pytest.mark.parametrize("damage", ["truncated metrics.json", "vol_pred.npy gone",
                                    "vol_pred.npy of another shape",
                                    "a metrics.json field of another type"])
def test_a_run_that_does_not_read_back_is_broken(damage, root, capsys):
    """The report names it (stderr and a section) and counts it nowhere; `experiment`
    calls it todo, not done before, and says why."""
    run = root / "results" / "table1" / "shepp" / "fdk"
    if damage == "truncated metrics.json":
        (run / "metrics.json").write_text((run / "metrics.json").read_text()[:100])
    elif damage == "vol_pred.npy gone":
        (run / "vol_pred.npy").unlink()
    elif damage == "a metrics.json field of another type":
        _edit_json(run / "metrics.json", lambda m: m["data"].update(n_voxel=[[12]]))
    else:
        np.save(run / "vol_pred.npy", np.zeros((4, 4, 4), np.float32))
    rc, err, _ = run_cli(["report", "--out", str(root / "results"), "--report",
                          str(root / "report" / "results.md")], capsys)
    assert rc == 0 and "table1/shepp/fdk is broken" in err, err
    md = (root / "report" / "results.md").read_text()
    assert "## Broken runs" in md and "`table1/shepp/fdk`" in md.split("## Broken runs")[1]
    row = next(line for line in md.splitlines() if line.startswith("| FDK |"))
    assert set(c.strip() for c in row.split("|")[2:-1]) == {"—"}, row
    from mi_grg.lab.runner import run_experiment
    res = run_experiment("table1", root / "suite.json", root / "results", methods="fdk",
                         dry_run=True, progress=False)
    err = capsys.readouterr().err
    assert [r["status"] for r in res["runs"]] == ["todo"] and "fdk is broken" in err, err


def test_a_finished_run_reads_back(root):
    """The reference for the test above: the undamaged run is finished and counted."""
    from mi_grg.lab.finished import run_problem
    from mi_grg.lab.runner import run_experiment
    assert run_problem(root / "results" / "table1" / "shepp" / "fdk") is None
    res = run_experiment("table1", root / "suite.json", root / "results", methods="fdk",
                         dry_run=True, progress=False)
    assert [r["status"] for r in res["runs"]] == ["done before"]


def test_a_full_disk_names_the_file_and_the_space(root, capsys, monkeypatch, tree_hash):
    """NumPy's own "N requested and M written" becomes the file being written (as it will
    be named in --out) and the free space; the earlier data set is kept whole."""
    import mi_grg.data.dataset as dataset
    real = np.save

    def full(path, arr, *a, **k):
        if "proj_train_0003" in str(path):
            Path(path).write_bytes(b"\x93NUMPY")
            raise OSError("32768 requested and 21396 written")
        return real(path, arr, *a, **k)
    monkeypatch.setattr(dataset.np, "save", full)
    before = tree_hash(root)
    rc, err, _ = run_cli(["simulate", "--n", "12", "--det", "12", "--views", "6",
                          "--test-views", "2", "--out", str(root / "data")], capsys)
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert f"{root / 'data' / 'proj_train' / 'proj_train_0003.npy'}: No space left" in err
    assert "free on the file system of" in err and "expected free disk space" in err
    assert tree_hash(root) == before


def test_the_dask_instructions_listen_on_loopback_only():
    """experiments/README.md starts scheduler, workers and their dashboards on 127.0.0.1
    (Dask's default is every interface)."""
    text = (ROOT / "experiments" / "README.md").read_text()
    lines = [line for line in text.splitlines() if line.startswith(".venv/bin/dask ")]
    assert {line.split()[1] for line in lines} == {"scheduler", "worker"}, lines
    for line in lines:
        assert "--host 127.0.0.1" in line and "--dashboard-address 127.0.0.1:" in line, line
    assert "tcp://127.0.0.1:8786" in next(line for line in lines if " worker " in line)


# ---------------------------------------------------------------- fuzzing
#: Cases per kind in the fast suite (scripts/fuzz_inputs.py runs many more).
FAST_CASES = 4


@pytest.mark.parametrize("kind", list(fuzz.KINDS))
def test_fuzzed_inputs(kind, pristine, tmp_path):
    """A few random truncations, byte flips and type changes of each input file kind: no
    traceback, one error line, no input or earlier output changed."""
    results = fuzz.fuzz(pristine, tmp_path, [kind], FAST_CASES, seed=0)
    assert [r for r in results if r["problems"]] == []
