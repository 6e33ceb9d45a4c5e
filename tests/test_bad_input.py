"""Bad input for `mi-grg import`, `reconstruct` and `simulate`: each broken input of the tables
below ends in exit status 2 and one line on stderr naming the culprit, with every input and
any earlier output byte-identical afterwards (the whole folder is hashed before and after).
Also: replacing an output is atomic (a failure mid-swap, a killed run) and no traceback
reaches the terminal."""
from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from mi_grg.cli import main

N_VIEWS, NV, NU = 8, 16, 16
DARK, FLAT = 100, 1100


# ---------------------------------------------------------------- inputs
def _counts():
    """Counts of a cylinder on the axis (the same in every view), free rays at the edges."""
    u = np.arange(NU) + 0.5 - NU / 2
    p = 0.8 * np.sqrt(np.clip(1 - (u / 5) ** 2, 0, None))
    return np.broadcast_to(DARK + (FLAT - DARK) * np.exp(-p), (NV, NU)).astype(np.uint16)


def _write_inputs(root: Path) -> None:
    """root/scan (FIPS text + 8 TIFFs), flats/, darks/, tiffs/ + scene.xml (a plain
    stack), an earlier import prev/, a simulated case data/ and an fdk run of it, run/."""
    from mi_grg.core.geometry import circular_angles
    from mi_grg.data.dataset import save_case
    from mi_grg.data.scene import Scan, scan_to_xml
    from mi_grg.data.simulate import default_geometry, simulate_case
    scan = root / "scan"
    scan.mkdir()
    (scan / "scan.txt").write_text(
        f"NumberImages = {N_VIEWS}\nAngleFirst = 0\nAngleInterval = {360 / N_VIEWS}\n"
        f"AngleLast = {360 - 360 / N_VIEWS}\nDistanceSourceDetector = 500\n"
        "DistanceSourceOrigin = 300\nPixelSize = 0.4\n")
    for folder, prefix, n, value in (("scan", "scan_", N_VIEWS, None), ("tiffs", "p_", N_VIEWS,
                                     None), ("flats", "flat_", 2, FLAT), ("darks", "dark_", 2,
                                                                          DARK)):
        (root / folder).mkdir(exist_ok=True)
        for i in range(n):
            img = _counts() if value is None else np.full((NV, NU), value, np.uint16)
            tifffile.imwrite(root / folder / f"{prefix}{i + 1:04d}.tif", img)
    geo = default_geometry(n=8, det=NU, views=N_VIEWS)
    (root / "scene.xml").write_text(scan_to_xml(Scan(geometry=geo.with_angles(
        circular_angles(N_VIEWS)))))
    assert main(["import", str(scan / "scan.txt"), "--out", str(root / "prev"),
                 "--nVoxel", "8"]) == 0
    save_case(simulate_case("shepp", geo, circular_angles(4) + 0.1), root / "data")
    assert main(["reconstruct", str(root / "data"), "--method", "fdk",
                 "--out", str(root / "run")]) == 0


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("pristine")
    _write_inputs(root)
    return root


def run_cli(argv, capsys) -> tuple:
    """(exit status, stderr) of mi_grg.cli.main run in-process."""
    try:
        rc = main(argv)
    except SystemExit as e:   # argparse's usage errors
        rc = e.code
    return rc, capsys.readouterr().err.strip()


# ---------------------------------------------------------------- breaking the inputs
def _gap_and_stray(r):        # views 1-3, 5-8 and a stray 9: the count still matches
    (r / "scan" / "scan_0004.tif").unlink()
    shutil.copy(r / "scan" / "scan_0001.tif", r / "scan" / "scan_0009.tif")


def _missing(r):
    (r / "scan" / "scan_0008.tif").unlink()


def _duplicate(r):
    shutil.copy(r / "scan" / "scan_0003.tif", r / "scan" / "scan_00003.tif")


def _tiff_gap(r):
    (r / "tiffs" / "p_0005.tif").rename(r / "tiffs" / "p_0009.tif")


def _truncated_pickle(r):
    blob = pickle.dumps({"DSD": 1.0, "image": np.zeros((8, 8, 8))}, protocol=5)
    (r / "scan.pickle").write_bytes(blob[:len(blob) // 2])


class _System:
    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def _hostile_pickle(r):
    (r / "evil.pickle").write_bytes(pickle.dumps(
        {"DSD": 1.0, "x": _System(f"echo owned > {r / 'owned'}")}, protocol=5))


def _a_file(r):
    (r / "notes.txt").write_text("not a folder")


def _other_folder(r):
    (r / "other").mkdir()
    (r / "other" / "thesis.tex").write_text("months of work")


def _truncated_checkpoint(r):
    np.savez(r / "run" / "checkpoint.npz", a=np.arange(1000))
    blob = (r / "run" / "checkpoint.npz").read_bytes()
    (r / "run" / "checkpoint.npz").write_bytes(blob[:len(blob) // 2])


def _corrupt_meta(r):
    (r / "data" / "meta_data.json").write_text('{"scanner": {"DSD": ')


def _missing_projection(r):
    (r / "data" / "proj_train" / "proj_train_0003.npy").unlink()


def _truncated_projection(r):
    p = r / "data" / "proj_train" / "proj_train_0002.npy"
    p.write_bytes(p.read_bytes()[:100])


def _empty_folder(r):
    (r / "empty").mkdir()


SCAN, FLATS, DARKS = "{r}/scan/scan.txt", "{r}/flats/*.tif", "{r}/darks/*.tif"
FIPS = [SCAN, "--nVoxel", "8"]

# name: (arguments, what to break first, what the one-line message must name)
IMPORT_CASES = {
    "out is the source's folder": (
        [SCAN, "--out", "{r}/scan", "--overwrite"], None, ["--out", "the input"]),
    "out holds the flats": (
        FIPS + ["--flats", FLATS, "--darks", DARKS, "--out", "{r}/flats", "--overwrite"],
        None, ["--out", "flat_0001.tif"]),
    "out is a parent of the source": (
        FIPS + ["--out", "{r}", "--overwrite"], None, ["--out", "holds the input"]),
    "out inside the FIPS scan's folder": (FIPS + ["--out", "{r}/scan/case2"], None,
                                          ["--out", "lies inside the input", "/scan"]),
    "out inside the flats' folder": (
        FIPS + ["--flats", FLATS, "--darks", DARKS, "--out", "{r}/flats/sub"], None,
        ["--out", "lies inside the input", "/flats"]),
    "out inside the darks' folder": (
        FIPS + ["--flats", FLATS, "--darks", DARKS, "--out", "{r}/darks/sub"], None,
        ["--out", "lies inside the input", "/darks"]),
    "out inside a TIFF folder source": (
        ["{r}/tiffs", "--scene", "{r}/scene.xml", "--out", "{r}/tiffs/case"], None,
        ["--out", "lies inside the input"]),
    "gap in the numbering plus a stray": (
        FIPS + ["--out", "{r}/new"], _gap_and_stray, ["missing scan_0004.tif", "scan_0009.tif"]),
    "a missing projection": (FIPS + ["--out", "{r}/new"], _missing, ["missing scan_0008.tif"]),
    "a duplicate projection number": (
        FIPS + ["--out", "{r}/new"], _duplicate, ["scan_0003.tif", "same projection number"]),
    "gap in a TIFF folder's numbering": (
        ["{r}/tiffs", "--scene", "{r}/scene.xml", "--out", "{r}/new"], _tiff_gap,
        ["missing p_0005.tif", "p_0009.tif"]),
    "--nVoxel 0": (FIPS[:1] + ["--nVoxel", "0", "--out", "{r}/new"], None, ["--nVoxel 0"]),
    "--bin larger than the detector": (FIPS + ["--bin", "1000", "--out", "{r}/new"], None,
                                       ["--bin 1000", "scan_0001.tif"]),
    "--cor at the detector's edge": (FIPS + ["--cor", "7.6", "--out", "{r}/new"], None,
                                     ["--cor 7.6", "--sVoxel"]),
    "--cor off the detector": (FIPS + ["--cor", "40", "--out", "{r}/new"], None, ["--cor 40"]),
    "volume above the memory limit": (
        FIPS[:1] + ["--nVoxel", "1200", "--sVoxel", "5", "--max-memory", "1", "--out",
                    "{r}/new"], None, ["--max-memory", "1200 x 1200 x 1200"]),
    "volume above one array's size": (
        FIPS[:1] + ["--nVoxel", "2000", "--sVoxel", "5", "--max-memory", "1e6", "--out",
                    "{r}/new"], None, ["--nVoxel", "2000 x 2000 x 2000", "one array"]),
    "--sVoxel negative": (FIPS + ["--sVoxel", "-1", "--out", "{r}/new"], None, ["--sVoxel -1"]),
    "darks brighter than flats": (
        FIPS + ["--flats", DARKS, "--darks", FLATS, "--out", "{r}/new"], None,
        ["--flats", "--darks", "not brighter than the mean dark"]),
    "darks brighter than the projections": (
        FIPS + ["--darks", FLATS, "--out", "{r}/new"], None,
        ["--free-ray auto", "scan_0001.tif", "dark level"]),
    "--flats matching nothing": (FIPS + ["--flats", "{r}/none_*.tif", "--out", "{r}/new"], None,
                                 ["--flats", "none_*.tif"]),
    "--free-ray reversed": (FIPS + ["--free-ray", "3:2", "--out", "{r}/new"], None,
                            ["--free-ray", "3:2"]),
    "--bin not a number": (FIPS + ["--bin", "x", "--out", "{r}/new"], None, ["--bin", "'x'"]),
    "source missing": (["{r}/nowhere.txt", "--out", "{r}/new"], None, ["nowhere.txt"]),
    "out is a file": (FIPS + ["--out", "{r}/notes.txt"], _a_file, ["--out", "is a file"]),
    "out below a file": (FIPS + ["--out", "{r}/notes.txt/case"], _a_file,
                         ["--out", "notes.txt is a file"]),
    "out exists, no --overwrite": (FIPS + ["--out", "{r}/prev"], None, ["--out", "--overwrite"]),
    "--overwrite of a folder that is no data set": (
        FIPS + ["--out", "{r}/other", "--overwrite"], _other_folder, ["--out", "meta_data.json"]),
    "bad scan with --overwrite of an earlier import": (
        FIPS + ["--out", "{r}/prev", "--overwrite"], _gap_and_stray, ["missing scan_0004.tif"]),
    "truncated pickle": (["{r}/scan.pickle", "--out", "{r}/new"], _truncated_pickle,
                         ["scan.pickle"]),
    "hostile pickle": (["{r}/evil.pickle", "--out", "{r}/new"], _hostile_pickle,
                       ["evil.pickle", "refuses the type posix.system"]),
}

RUN = ["--out", "{r}/run"]
RECONSTRUCT_CASES = {
    "data missing": (["{r}/nowhere", "--method", "fdk"] + RUN, None, ["nowhere"]),
    "data without meta_data.json": (["{r}/empty", "--method", "fdk"] + RUN, _empty_folder,
                                    ["meta_data.json"]),
    "corrupt meta_data.json": (["{r}/data", "--method", "fdk"] + RUN, _corrupt_meta,
                               ["meta_data.json"]),
    "a missing projection": (["{r}/data", "--method", "fdk"] + RUN, _missing_projection,
                             ["proj_train_0003.npy"]),
    "a truncated projection": (["{r}/data", "--method", "fdk"] + RUN, _truncated_projection,
                               ["proj_train_0002.npy"]),
    "out is the data": (["{r}/data", "--method", "fdk", "--out", "{r}/data"], None,
                        ["--out", "is the input"]),
    "out inside the data": (["{r}/data", "--method", "fdk", "--out", "{r}/data/run"], None,
                            ["--out", "lies inside the input"]),
    "out is a file": (["{r}/data", "--method", "fdk", "--out", "{r}/notes.txt"], _a_file,
                      ["--out", "is a file"]),
    "out is a folder that is no earlier run": (["{r}/data", "--method", "fdk", "--out",
                                                "{r}/other"], _other_folder,
                                               ["--out", "metrics.json", "checkpoint.npz"]),
    "--option without =": (["{r}/data", "--method", "sart", "--option", "foo"] + RUN, None,
                           ["--option 'foo'", "KEY=VALUE"]),
    "--option n_iter=abc": (["{r}/data", "--method", "sart", "--option", "n_iter=abc",
                             "--option", "stop=none"] + RUN, None, ["n_iter=abc"]),
    "--option nonneg=maybe": (["{r}/data", "--method", "sart", "--option", "nonneg=maybe"]
                              + RUN, None, ["nonneg=maybe", "true or false"]),
    "unknown option": (["{r}/data", "--method", "fdk", "--option", "bogus=1"] + RUN, None,
                       ["bogus"]),
    "unknown method": (["{r}/data", "--method", "nope"] + RUN, None, ["nope"]),
    "--config missing": (["{r}/data", "--method", "gr", "--config", "{r}/none.xml"] + RUN, None,
                         ["none.xml"]),
    "truncated checkpoint.npz with --resume": (
        ["{r}/data", "--method", "gr", "--resume", "--option", "iterations=20", "--option",
         "holdout_every=0", "--option", "n_points=200"] + RUN, _truncated_checkpoint,
        ["checkpoint.npz", "truncated"]),
}


TINY = ["--n", "8", "--det", "12", "--views", "4", "--test-views", "0"]
SIMULATE_CASES = {
    "out holds the scene": (["--scene", "{r}/scene.xml", "--out", "{r}"], None,
                            ["--out", "holds the input", "scene.xml"]),
    "out is a folder that is no data set": (TINY + ["--out", "{r}/other"], _other_folder,
                                            ["--out", "meta_data.json"]),
    "out is a file": (TINY + ["--out", "{r}/notes.txt"], _a_file, ["--out", "is a file"]),
}


def _check_refused(command, cases, name, root, capsys, tree_hash):
    argv, breaks, culprits = cases[name]
    if breaks:
        breaks(root)
    before = tree_hash(root)
    rc, err = run_cli([command, *(a.replace("{r}", str(root)) for a in argv)], capsys)
    assert rc == 2, (rc, err)
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"mi-grg {command}: error: ") or \
        err.startswith(f"mi-grg {command}: error: argument"), err
    for c in culprits:
        assert c in err, (c, err)
    assert tree_hash(root) == before   # inputs and earlier outputs untouched, no temporaries


@pytest.mark.parametrize("name", list(IMPORT_CASES))
def test_import_refuses(name, root, capsys, tree_hash):
    _check_refused("import", IMPORT_CASES, name, root, capsys, tree_hash)


@pytest.mark.parametrize("name", list(RECONSTRUCT_CASES))
def test_reconstruct_refuses(name, root, capsys, tree_hash):
    _check_refused("reconstruct", RECONSTRUCT_CASES, name, root, capsys, tree_hash)


@pytest.mark.parametrize("name", list(SIMULATE_CASES))
def test_simulate_refuses(name, root, capsys, tree_hash):
    _check_refused("simulate", SIMULATE_CASES, name, root, capsys, tree_hash)


def test_simulate_replaces_an_earlier_data_set_whole(root, capsys):
    """Not a merge: a file of the earlier data set that the new one lacks is gone."""
    stray = root / "data" / "proj_train" / "proj_train_0099.npy"
    shutil.copy(root / "data" / "proj_train" / "proj_train_0000.npy", stray)
    rc, err = run_cli(["simulate", *TINY, "--out", f"{root}/data"], capsys)
    assert rc == 0, err
    assert not stray.exists() and len(list((root / "data" / "proj_train").iterdir())) == 4
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


def test_the_inputs_themselves_import(root, capsys):
    """The unbroken inputs of the tables pass: the refusals above are about the breakage."""
    for argv in (FIPS + ["--flats", FLATS, "--darks", DARKS, "--out", "{r}/a"],
                 ["{r}/tiffs", "--scene", "{r}/scene.xml", "--out", "{r}/b", "--nVoxel", "8"],
                 FIPS + ["--out", "{r}/prev", "--overwrite", "--sVoxel", "5"]):
        rc, err = run_cli(["import", *(a.replace("{r}", str(root)) for a in argv)], capsys)
        assert rc == 0, err
    rc, err = run_cli(["reconstruct", f"{root}/data", "--method", "sart", "--option",
                       "n_iter=2", "--option", "stop=none", "--out", f"{root}/run"], capsys)
    assert rc == 0, err
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------- atomic replacement
def test_failed_swap_leaves_the_old_output(root, capsys, monkeypatch, tree_hash):
    """The new case is complete but moving it into place fails (as on a read-only
    folder): the earlier import is back, byte for byte, and nothing temporary is left."""
    import mi_grg.data.outputs as outputs
    before = tree_hash(root)
    real = os.rename

    def failing(src, dst):
        if ".import-" in str(src):
            raise PermissionError(13, "Permission denied", str(dst))
        return real(src, dst)
    monkeypatch.setattr(outputs.os, "rename", failing)
    rc, err = run_cli(["import", *(a.replace("{r}", str(root)) for a in FIPS),
                       "--sVoxel", "5", "--out", f"{root}/prev", "--overwrite"], capsys)
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "prev" in err and "Permission denied" in err
    assert tree_hash(root) == before


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_killed_replacement_is_repaired_on_the_next_run(root, capsys, tree_hash):
    """A run killed between its two renames leaves the old output aside and a temporary:
    the next run puts the old output back and removes the temporary (and says so)."""
    pid = _dead_pid()
    old = root / f".prev.old-{pid}"
    (root / "prev").rename(old)
    shutil.copytree(root / "run", root / f".prev.import-{pid}")
    expected = tree_hash(old)
    rc, err = run_cli(["import", *(a.replace("{r}", str(root)) for a in FIPS),
                       "--out", f"{root}/prev"], capsys)
    # the repaired output exists again, so this run (without --overwrite) is refused
    assert rc == 2 and "--overwrite" in err.splitlines()[-1]
    assert "restored" in err and "removed" in err
    assert tree_hash(root / "prev") == expected
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


def test_a_killed_import_leaves_no_lasting_temporary(root, capsys, tree_hash):
    pid = _dead_pid()
    (root / f".prev.import-{pid}").mkdir()
    (root / f".prev.import-{pid}" / "meta_data.json").write_text("{")
    before = tree_hash(root / "prev")
    rc, err = run_cli(["import", *(a.replace("{r}", str(root)) for a in FIPS), "--sVoxel", "5",
                       "--out", f"{root}/prev", "--overwrite"], capsys)
    assert rc == 0, err
    assert tree_hash(root / "prev") != before     # replaced
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


def test_a_temporary_that_cannot_be_removed_is_named(root, capsys, monkeypatch):
    """A leftover that even the next run cannot remove (e.g. read-only) is named on
    stderr and does not stop that run."""
    import mi_grg.data.outputs as outputs
    pid = _dead_pid()
    (root / f".prev.old-{pid}").mkdir()
    real = shutil.rmtree

    def failing(path, *a, **k):
        if f".prev.old-{pid}" in str(path):
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *a, **k)
    monkeypatch.setattr(outputs.shutil, "rmtree", failing)
    rc, err = run_cli(["import", *(a.replace("{r}", str(root)) for a in FIPS), "--sVoxel", "5",
                       "--out", f"{root}/prev", "--overwrite"], capsys)
    assert rc == 0, err
    assert f".prev.old-{pid}" in err and "remove it by hand" in err


# ---------------------------------------------------------------- no traceback
def test_no_traceback_in_a_real_process(root, tree_hash):
    """The installed entry point, as a user runs it: one line on stderr, exit 2."""
    for argv in (["import", *(a.replace("{r}", str(root)) for a in FIPS),
                  "--out", f"{root}/scan", "--overwrite"],
                 ["reconstruct", f"{root}/data", "--method", "sart", "--option", "foo",
                  "--out", f"{root}/run"]):
        before = tree_hash(root)
        res = subprocess.run([sys.executable, "-m", "mi_grg.cli", *argv], capture_output=True,
                             text=True, timeout=300)
        assert res.returncode == 2, res.stderr
        assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1, \
            res.stderr
        assert tree_hash(root) == before
