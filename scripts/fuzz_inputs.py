"""Fuzz every input file kind of the mi-grg commands: random truncations, byte flips and
type changes, each handed to the command that reads the file.

    .venv/bin/python scripts/fuzz_inputs.py [--per-kind N] [--seed S] [--kinds a,b]
                                            [--json docs/bench/fuzz_inputs.json]

A workspace is built once (a simulated data set with EXR copies, an fdk run, a gr run with
its checkpoint and Gaussians, a render of it, a FIPS scan with flats and darks and an
earlier import, a NAF pickle, a suite, a results folder and its report, a scene and a
training config). Each case copies it, mutates one file of one kind (``KINDS``) and runs
the command that reads it, in this process, under ``--max-memory``. A case passes when

* the command returns (no exception escapes ``mi_grg.cli.main``), with exit status 0 (or
  1 where render says that a view failed), or 2 and an error line
  ``mi-grg CMD: error: ...`` of at most ``MAX_MESSAGE`` characters;
* nothing on stderr is a Python traceback;
* no byte outside the command's ``--out`` changed, and on a failure nothing at all (no
  earlier output, no temporary left beside it).

tests/test_fuzz_inputs.py runs a few cases of every kind in the fast suite; this script
runs many (docs/robustness.md quotes its counts).
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import pickle
import shutil
import signal
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

#: Limit of every fuzzed command (GiB): a mutated size fails fast instead of running long.
MAX_MEMORY = "2"
#: Seconds one case may take (a hang is a failure, not a stuck fuzzer).
CASE_SECONDS = 240
#: Values a type change puts in place of a JSON / pickle field.
VALUES = (None, True, False, 0, -1, 1e308, -1e308, 2 ** 62, 0.5, "", "x", "nan", [], {},
          [1, 2, 3], [[1]], {"a": 1}, "1 2 3", "z" * 100_000)
#: Tokens an XML attribute or a text field may become.
TOKENS = ("", "abc", "-1", "0", "1e400", "nan", "inf", "1 2", "16 16 16 16", "true", "none",
          "1e9", "3.5", "x" * 100_000)
#: What an array may become (npy, npz, pickle, TIFF).
DTYPES = (np.int64, np.int16, np.uint8, np.float16, np.float64, np.complex64, np.bool_)

GR = ["--method", "gr", "--option", "iterations=10", "--option", "n_points=100",
      "--option", "holdout_every=0", "--option", "refine=none", "--option", "progress=false",
      "--option", "checkpoint_every=5"]
CFG = ["--option", "iterations=2", "--option", "n_points=50", "--option", "holdout_every=0",
       "--option", "refine=none", "--option", "progress=false"]
IMPORT = ["import", "{r}/scan/scan.txt", "--nVoxel", "8", "--flats", "{r}/flats/*.tif",
          "--darks", "{r}/darks/*.tif", "--out", "{r}/prev", "--overwrite"]
RENDER = ["render", "--run", "{r}/gr", "--out", "{r}/render", "--spp", "2", "--det", "8",
          "--views", "1"]
RECONSTRUCT = ["reconstruct", "{r}/data", "--method", "fdk", "--out", "{r}/run"]
REPORT = ["report", "--out", "{r}/results", "--report", "{r}/report/results.md"]

# kind: (file to mutate, how, command, its --out)
KINDS = {
    "meta_data.json": ("data/meta_data.json", "json", RECONSTRUCT, "run"),
    "projection .npy": ("data/proj_train/proj_train_0001.npy", "npy", RECONSTRUCT, "run"),
    "projection .exr": ("data/proj_train/proj_train_0002.exr", "bytes", RECONSTRUCT, "run"),
    "vol_gt.npy": ("data/vol_gt.npy", "npy", RECONSTRUCT, "run"),
    "scene XML": ("scene.xml", "xml", ["simulate", "--scene", "{r}/scene.xml", "--out",
                                       "{r}/sim"], "sim"),
    "config XML": ("config.xml", "xml", ["reconstruct", "{r}/data", "--method", "gr",
                                         "--config", "{r}/config.xml", *CFG, "--out",
                                         "{r}/gr_cfg"], "gr_cfg"),
    "suite JSON": ("suite.json", "json", ["experiment", "table1", "--suite", "{r}/suite.json",
                                          "--out", "{r}/results", "--dry-run"], "results"),
    "gaussians.npz": ("gr/gaussians.npz", "npz", RENDER, "render"),
    "checkpoint.npz": ("gr/checkpoint.npz", "npz", ["reconstruct", "{r}/data", *GR,
                                                    "--resume", "--out", "{r}/gr"], "gr"),
    "NAF pickle": ("naf.pickle", "pickle", ["import", "{r}/naf.pickle", "--out",
                                            "{r}/naf_case"], "naf_case"),
    "FIPS scan.txt": ("scan/scan.txt", "text", IMPORT, "prev"),
    "projection TIFF": ("scan/scan_0003.tif", "tif", IMPORT, "prev"),
    "flat TIFF": ("flats/flat_0001.tif", "tif", IMPORT, "prev"),
    "metrics.json (report)": ("results/table1/shepp/fdk/metrics.json", "json", REPORT,
                              "report"),
    "runs.json (report)": ("results/table1/runs.json", "json", REPORT, "report"),
    "gr metrics.json (report)": ("results/table1/shepp/gr/metrics.json", "json", REPORT,
                                  "report"),
    "metrics.json (experiment)": ("results/table1/shepp/gr/metrics.json", "json",
                                  ["experiment", "table1", "--suite", "{r}/suite.json", "--out",
                                   "{r}/results", "--dry-run"], "results"),
    "metrics.json (render)": ("gr/metrics.json", "json", RENDER, "render"),
}


class CaseTimeout(Exception):
    """A case ran past CASE_SECONDS."""


def cli(argv) -> tuple:
    """(exit status, stderr, escaped exception or None) of mi_grg.cli.main in-process."""
    from mi_grg.cli import main
    err, out = io.StringIO(), io.StringIO()
    escaped = None
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = main(list(argv))
        except SystemExit as e:        # argparse's usage errors
            rc = e.code if isinstance(e.code, int) else 2
        except CaseTimeout:
            raise
        except BaseException as e:     # noqa: BLE001 (a traceback: what the fuzzer hunts)
            rc, escaped = None, f"{type(e).__name__}: {str(e)[:300]}"
    return rc, err.getvalue(), escaped


# ---------------------------------------------------------------- the workspace
def _fips(root: Path) -> None:
    """scan/ (FIPS text + 8 TIFFs of a cylinder), flats/, darks/ and an import, prev/."""
    import tifffile
    (root / "scan").mkdir()
    (root / "scan" / "scan.txt").write_text(
        "NumberImages = 8\nAngleFirst = 0\nAngleInterval = 45\nAngleLast = 315\n"
        "DistanceSourceDetector = 500\nDistanceSourceOrigin = 300\nPixelSize = 0.4\n")
    u = np.arange(16) + 0.5 - 8
    counts = 100 + 1000 * np.exp(-0.8 * np.sqrt(np.clip(1 - (u / 5) ** 2, 0, None)))
    frame = np.broadcast_to(counts, (16, 16)).astype(np.uint16)
    for folder, prefix, n, value in (("scan", "scan_", 8, None), ("flats", "flat_", 2, 1100),
                                     ("darks", "dark_", 2, 100)):
        (root / folder).mkdir(exist_ok=True)
        for i in range(n):
            img = frame if value is None else np.full((16, 16), value, np.uint16)
            tifffile.imwrite(root / folder / f"{prefix}{i + 1:04d}.tif", img)


def _naf(root: Path) -> None:
    from mi_grg.core.geometry import circular_angles
    rng = np.random.default_rng(0)
    data = {"DSD": 1500.0, "DSO": 1000.0, "nDetector": [16, 16], "dDetector": [1.0, 1.0],
            "nVoxel": [8] * 3, "dVoxel": [1.0] * 3, "offOrigin": [0, 0, 0],
            "offDetector": [0, 0], "mode": "cone", "numTrain": 8, "numVal": 4,
            "train": {"projections": rng.random((8, 16, 16)).astype(np.float32),
                      "angles": circular_angles(8)},
            "val": {"projections": rng.random((4, 16, 16)).astype(np.float32),
                    "angles": circular_angles(4) + 0.1},
            "image": rng.random((8,) * 3).astype(np.float32)}
    (root / "naf.pickle").write_bytes(pickle.dumps(data, protocol=4))


def _results(root: Path, run) -> None:
    """results/ (table1: an fdk run and a copy of the gr run, its runs.json) and its
    report, report/."""
    d = root / "results" / "table1" / "shepp"
    assert run(["reconstruct", f"{root}/data", "--method", "fdk", "--out", str(d / "fdk")]) == 0
    shutil.copytree(root / "gr", d / "gr")
    (root / "results" / "table1" / "runs.json").write_text(json.dumps({"runs": [
        {"case": "shepp", "run": m, "category": "HO", "label": m, "method": m, "views": 6}
        for m in ("fdk", "gr")]}))
    assert run(["report", "--out", f"{root}/results", "--report",
                f"{root}/report/results.md"]) == 0


def build(root: Path) -> Path:
    """The pristine workspace (see the module docstring)."""
    from mi_grg.training.config import make_config, write_config_xml
    root.mkdir(parents=True, exist_ok=True)

    def run(argv):
        rc, err, escaped = cli(argv)
        assert rc == 0 and escaped is None, (argv, rc, err, escaped)
        return rc
    run(["simulate", "--n", "12", "--det", "12", "--views", "6", "--test-views", "2", "--exr",
         "--out", f"{root}/data"])
    meta = json.loads((root / "data" / "meta_data.json").read_text())
    meta["proj_train"][2]["file_path"] = "proj_train/proj_train_0002.exr"   # read as EXR
    (root / "data" / "meta_data.json").write_text(json.dumps(meta, indent=1))
    shutil.copy(root / "data" / "scene.xml", root / "scene.xml")
    run(["simulate", "--scene", f"{root}/scene.xml", "--out", f"{root}/sim"])
    run([a.replace("{r}", str(root)) for a in RECONSTRUCT])
    run(["reconstruct", f"{root}/data", *GR, "--out", f"{root}/gr"])
    run([a.replace("{r}", str(root)) for a in RENDER])
    _fips(root)
    run([a.replace("{r}", str(root)) for a in IMPORT])
    _naf(root)
    (root / "suite.json").write_text(json.dumps({
        "name": "fuzz", "variant": "llvm_ad_mono",
        "method_options": {"sart": {"n_iter": 2, "stop": "none"}},
        "experiments": {"table1": {"methods": ["fdk", "sart", "gr"]}},
        "cases": [{"name": "shepp", "category": "HO", "source": "shepp", "views": 6,
                   "test_views": 2, "n": 12, "det": 12, "mode": "cone", "noise": None,
                   "seed": 0}]}, indent=1))
    write_config_xml(make_config("gr"), root / "config.xml", "gr")
    _results(root, run)
    return root


# ---------------------------------------------------------------- mutations
def _bytes(data: bytes, rng) -> bytes:
    op = rng.integers(3)
    if op == 0 or len(data) < 2:                         # truncated (possibly empty)
        return data[:int(rng.integers(0, max(len(data), 1)))]
    if op == 1:                                          # a few bytes flipped
        b = bytearray(data)
        for i in rng.integers(0, len(b), int(rng.integers(1, 9))):
            b[i] = int(rng.integers(256))
        return bytes(b)
    return data + bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8))


def _paths(obj, prefix=()):
    """Every (path) into a tree of dicts and lists (arrays are leaves)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _replace(obj, path, value):
    if not path:
        return value
    obj[path[0]] = _replace(obj[path[0]], path[1:], value)
    return obj


def _array(a: np.ndarray, rng) -> np.ndarray:
    """A changed copy of an array: dtype, shape or values."""
    op = rng.integers(3)
    if op == 0:
        return a.astype(DTYPES[rng.integers(len(DTYPES))])
    if op == 1:
        shapes = [a.ravel(), a[None], a.T, a[..., :-1] if a.ndim and a.shape[-1] > 1 else a,
                  np.zeros((0,), a.dtype), np.zeros(3, a.dtype)]
        return np.asarray(shapes[rng.integers(len(shapes))])
    b = np.array(a, np.float64 if a.dtype.kind != "c" else a.dtype, copy=True)
    if b.size:
        b.flat[rng.integers(0, b.size, max(1, b.size // 10))] = \
            (np.nan, np.inf, -1e30, 1e30, -1.0)[rng.integers(5)]
    return b


def _tree(obj, rng):
    """A type change (or deletion) of one field of a dict/list tree."""
    paths = list(_paths(obj))
    path = paths[rng.integers(len(paths))]
    if path and rng.random() < 0.2:
        parent = obj
        for k in path[:-1]:
            parent = parent[k]
        del parent[path[-1]]
        return obj
    here = obj
    for k in path:
        here = here[k]
    if isinstance(here, np.ndarray) and rng.random() < 0.7:
        return _replace(obj, path, _array(here, rng))
    return _replace(obj, path, VALUES[rng.integers(len(VALUES))])


def mutate_json(path: Path, rng) -> None:
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
    elif rng.random() < 0.1:
        path.write_text("[" * 200_000 + "]" * 200_000)
    else:
        path.write_text(json.dumps(_tree(json.loads(path.read_text()), rng)))


def mutate_xml(path: Path, rng) -> None:
    if rng.random() < 0.25:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    tree = ET.parse(path)
    elements = list(tree.getroot().iter())
    el = elements[rng.integers(len(elements))]
    op = rng.integers(5)
    if op == 0 and el.attrib:
        el.set(sorted(el.attrib)[rng.integers(len(el.attrib))], TOKENS[rng.integers(len(TOKENS))])
    elif op == 1 and el.attrib:
        del el.attrib[sorted(el.attrib)[rng.integers(len(el.attrib))]]
    elif op == 2:
        el.tag = ("float", "integer", "string", "boolean", "bogus", "shape")[rng.integers(6)]
    elif op == 3:
        parent = next((p for p in elements if el in list(p)), None)
        if parent is not None:
            parent.remove(el) if rng.random() < 0.5 else parent.append(el)
    else:
        tree.getroot().extend(ET.Element("shape", type="sphere") for _ in range(20_000))
    tree.write(path)


def mutate_npy(path: Path, rng) -> None:
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    arr = np.load(path, allow_pickle=False)
    with open(path, "wb") as f:
        np.save(f, _array(arr, rng))


def mutate_npz(path: Path, rng) -> None:
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    key = sorted(arrays)[rng.integers(len(arrays))]
    op = rng.integers(3)
    if op == 0:
        del arrays[key]
    elif op == 1 and key == "meta":
        meta = json.loads(bytes(arrays["meta"]).decode())
        arrays["meta"] = np.frombuffer(json.dumps(_tree(meta, rng)).encode(), np.uint8)
    else:
        arrays[key] = _array(arrays[key], rng)
    np.savez(path, **arrays)


def mutate_pickle(path: Path, rng) -> None:
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    data = pickle.loads(path.read_bytes())     # our own file: safe to load here
    path.write_bytes(pickle.dumps(_tree(data, rng), protocol=4))


def mutate_text(path: Path, rng) -> None:
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    lines = path.read_text().splitlines()
    i = int(rng.integers(len(lines)))
    op = rng.integers(3)
    if op == 0:
        del lines[i]
    elif op == 1:
        lines[i] = lines[i].split("=")[0] + "= " + TOKENS[rng.integers(len(TOKENS))]
    else:
        lines.insert(i, lines[i].split("=")[0] + "= 7")
    path.write_text("\n".join(lines) + "\n")


def mutate_tif(path: Path, rng) -> None:
    import tifffile
    if rng.random() < 0.3:
        path.write_bytes(_bytes(path.read_bytes(), rng))
        return
    tifffile.imwrite(path, _array(tifffile.imread(path), rng))


def mutate(path: Path, how: str, rng) -> None:
    {"json": mutate_json, "xml": mutate_xml, "npy": mutate_npy, "npz": mutate_npz,
     "pickle": mutate_pickle, "text": mutate_text, "tif": mutate_tif,
     "bytes": lambda p, r: p.write_bytes(_bytes(p.read_bytes(), r))}[how](path, rng)


# ---------------------------------------------------------------- one case
def tree_hash(folder: Path) -> dict:
    return {str(p.relative_to(folder)): None if p.is_dir() else
            hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*"))}


def _alarm(signum, frame):
    raise CaseTimeout(f"over {CASE_SECONDS} s")


def run_case(pristine: Path, work: Path, kind: str, index: int, seed: int) -> dict:
    """Mutate ``kind``'s file in a fresh copy of the workspace, run its command, judge."""
    from mi_grg.cli import MAX_MESSAGE
    target, how, argv, out = KINDS[kind]
    root = work / f"case{index}"
    shutil.rmtree(root, ignore_errors=True)
    shutil.copytree(pristine, root, symlinks=True)
    rng = np.random.default_rng([seed, index, sum(map(ord, kind))])
    mutate(root / target, how, rng)
    before = tree_hash(root)
    argv = [a.replace("{r}", str(root)) for a in argv] + (
        ["--max-memory", MAX_MEMORY] if argv[0] not in ("report", "import") else [])
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(CASE_SECONDS)
    t0 = time.perf_counter()
    try:
        rc, err, escaped = cli(argv)
    except CaseTimeout as e:
        rc, err, escaped = None, "", f"timeout {e}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    after = tree_hash(root)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    ok_codes = (0, 1) if argv[0] == "render" else (0,)
    allowed = out if rc in ok_codes else None
    outside = [k for k in changed if allowed is None or not
               (k == allowed or k.startswith(allowed + "/"))]
    lines = err.strip().splitlines()
    problems = []
    if escaped:
        problems.append(f"escaped {escaped}")
    if "Traceback" in err or 'File "' in err:
        problems.append("traceback on stderr")
    if rc == 2 and not (lines and lines[-1].startswith(f"mi-grg {argv[0]}: error: ")
                        and len(lines[-1]) <= MAX_MESSAGE + 40):
        problems.append(f"error line: {lines[-1][:200] if lines else '(none)'}")
    if rc not in (*ok_codes, 2) and not escaped:
        problems.append(f"exit status {rc}")
    if outside:
        problems.append(f"changed {outside[:5]}")
    shutil.rmtree(root, ignore_errors=True)
    return {"kind": kind, "index": index, "rc": rc, "problems": problems,
            "error": lines[-1][:300] if lines else "", "seconds": time.perf_counter() - t0}


def fuzz(pristine: Path, work: Path, kinds, per_kind: int, seed: int, progress=None) -> list:
    results = []
    for kind in kinds:
        for i in range(per_kind):
            results.append(run_case(pristine, work, kind, i, seed))
            if progress:
                progress(results[-1])
    return results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--per-kind", type=int, default=60)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--kinds", help="comma-separated kinds (default all)")
    p.add_argument("--work", default="/tmp/mi_grg_fuzz")
    p.add_argument("--json", help="write the counts and every failure here")
    a = p.parse_args(argv)
    kinds = a.kinds.split(",") if a.kinds else list(KINDS)
    work = Path(a.work)
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    pristine = build(work / "pristine")

    def show(r):
        mark = ("FAIL " + "; ".join(r["problems"]) if r["problems"] else
                f"rc {r['rc']}  {r['error'][:110]}")
        print(f"{r['kind']:24s} #{r['index']:<4d} {r['seconds']:6.1f} s  {mark}", flush=True)
    results = fuzz(pristine, work, kinds, a.per_kind, a.seed, show)
    failures = [r for r in results if r["problems"]]
    summary = {"cases": len(results), "per_kind": a.per_kind, "seed": a.seed,
               "kinds": {k: {"cases": sum(r["kind"] == k for r in results),
                             "exit_0_or_1": sum(r["kind"] == k and r["rc"] in (0, 1)
                                                for r in results),
                             "refused": sum(r["kind"] == k and r["rc"] == 2 for r in results),
                             "failures": sum(r["kind"] == k and bool(r["problems"])
                                             for r in results)} for k in kinds},
               "failures": failures, "seconds": time.perf_counter() - t0}
    print(f"{len(results)} cases, {len(failures)} failures, {summary['seconds']:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps(summary, indent=1) + "\n")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
