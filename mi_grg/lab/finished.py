"""A run is finished only when it reads back, and the report writes over nothing else.

``run_problem`` says why a run folder does not read back: its metrics.json must parse to
an object, and when it records the volume's size (``nVoxel``; every run that
``mi_grg.methods.reconstruct`` wrote does) the volume files it names (``volume_files``,
else ``vol_pred.npy``) must exist whole with that shape (a record's copy, ``record_of``,
keeps no volume: ``mi_grg.lab.record``). The report counts only such runs
and lists the others as broken (``read_finished``, ``broken_md``); ``mi-grg experiment``
runs them again (``is_finished``), naming each once.

``report_target`` is the rule for ``mi-grg report``: the results folder must hold runs,
and the report file and its image folder may not be, hold or lie inside anything the
runner wrote (``OUT/data``, ``OUT/suite.json``, the experiments' folders).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

METRICS = "metrics.json"
#: The volume a run wrote before metrics.json recorded its files.
DEFAULT_VOLUME = "vol_pred.npy"
#: How every report begins (``mi_grg.lab.report._intro_md``): an earlier report.
REPORT_HEAD = "# Results"

_NUMBER, _NONE = (int, float), type(None)
#: The fields of metrics.json that the report and the staleness check read, with the types
#: ``mi_grg.methods.reconstruct`` writes them in (each may be absent; "*": every key).
SCHEMA = {"method": str, "options": dict, "seconds": _NUMBER, "n_train_views": int,
          "nVoxel": list, "geometry": dict, "psnr_3d": _NUMBER, "ssim_3d": _NUMBER,
          "volume_files": [str], "record_of": str, "machine": {"*": (str, int, float, _NONE)},
          "data": {"n_voxel": [int], "n_detector": [int], "mode": str},
          "method_info": {"iterations_run": int, "iterations_planned": (int, _NONE),
                          "protocol": str, "stopped_by": (str, _NONE),
                          "best_iteration": (int, _NONE), "kept_iteration": (int, _NONE),
                          "iteration_rule": str, "held_out_views": [int], "config": dict,
                          "views": dict, "schedule": {"densify_stop": _NUMBER},
                          "stop_rule": {"noise": _NUMBER, "holdout_every": int},
                          "chosen": {"setting": {"*": _NUMBER}},
                          "oracle": {"psnr_3d_best": (int, float, _NONE),
                                     "gap_db": (int, float, _NONE)}}}

_named: set = set()


def _mismatch(value, schema, where: str) -> str | None:
    """Where ``value`` departs from ``schema`` (a type or tuple of types, [item schema],
    or {key: schema}), or None."""
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            return f"{where} is not an object"
        for key, sub in schema.items():
            for k in (value if key == "*" else [key] if key in value else []):
                found = _mismatch(value[k], sub, f"{where}.{k}".lstrip("."))
                if found:
                    return found
        return None
    if isinstance(schema, list):
        if not isinstance(value, list):
            return f"{where} is not a list"
        return next((f for f in (_mismatch(v, schema[0], f"{where}[{i}]")
                                 for i, v in enumerate(value)) if f), None)
    kinds = schema if isinstance(schema, tuple) else (schema,)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        return f"{where} is {type(value).__name__}, not {' or '.join(k.__name__ for k in kinds)}"
    return None


def _npy_shape(path: Path) -> tuple:
    """The shape of a whole .npy file (mapped, not read: a truncated one fails)."""
    arr = np.load(path, mmap_mode="r", allow_pickle=False)
    shape = arr.shape
    del arr
    return shape


def _volume_shape(path: Path) -> tuple:
    """[x, y, z] of a volume file the contract writes (.npy, ImageJ .tif, .nii.gz)."""
    if path.suffix == ".npy":
        return _npy_shape(path)
    if path.suffix == ".tif":
        import tifffile
        with tifffile.TiffFile(path) as tif:
            return tuple(reversed(tif.series[0].shape))     # pages z, rows y, columns x
    import nibabel
    return tuple(nibabel.load(path).shape)


def run_problem(run_dir) -> str | None:
    """None when the run at ``run_dir`` reads back (see the module docstring), else what
    is wrong with it (one line)."""
    from mi_grg.data.inputs import read_json
    d = Path(run_dir)
    try:
        m = read_json(d / METRICS, METRICS)
    except FileNotFoundError:
        return f"no {METRICS}"
    except (OSError, ValueError) as e:
        return str(e)
    if not isinstance(m, dict):
        return f"{d / METRICS}: expected an object, got {type(m).__name__}"
    wrong = _mismatch(m, SCHEMA, "")
    if wrong:
        return f"{d / METRICS}: {wrong}"[:300]
    if "nVoxel" not in m or "record_of" in m:
        return None       # names no volume: written by other tools, or mi_grg.lab.record
    shape = m["nVoxel"]
    if not (isinstance(shape, list) and len(shape) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)):
        return f"{d / METRICS}: nVoxel must be 3 positive integers, got {shape!r}"[:300]
    files = m.get("volume_files", [DEFAULT_VOLUME])
    if not (isinstance(files, list) and files and all(
            isinstance(f, str) and f and Path(f).name == f for f in files)):
        return f"{d / METRICS}: volume_files must list file names, got {files!r}"[:300]
    for name in files:
        try:
            got = _volume_shape(d / name)
        except FileNotFoundError:
            return f"{d / name} is missing"
        except Exception as e:   # noqa: BLE001 (any reader's error: the file is damaged)
            return f"{d / name}: unreadable ({type(e).__name__}: {e})"[:300]
        if list(got) != shape:
            return f"{d / name} has shape {list(got)}, {METRICS} says nVoxel {shape}"
    return None


def is_finished(run_dir) -> bool:
    """Whether the run reads back; a broken one (its metrics.json there, but not whole) is
    named on stderr, once per process."""
    problem = run_problem(run_dir)
    if problem is not None and (Path(run_dir) / METRICS).exists() and \
            str(run_dir) not in _named:
        _named.add(str(run_dir))
        print(f"note: {run_dir} is broken ({problem}); it runs again", file=sys.stderr)
    return problem is None


def read_finished(run_dir, row: dict):
    """The metrics of a run that reads back, else None; a broken run (metrics.json there,
    but not whole) is marked in ``row`` (status "broken", the reason)."""
    from mi_grg.data.inputs import read_json
    problem = run_problem(run_dir)
    if problem is None:
        return read_json(Path(run_dir) / METRICS, METRICS)
    if (Path(run_dir) / METRICS).exists():
        row["status"], row["broken"] = "broken", problem
    return None


def broken_md(all_rows: dict) -> list:
    """The report's list of broken runs (each also named on stderr): counted nowhere."""
    broken = [(exp, r) for exp, rows in all_rows.items() for r in rows
              if r.get("status") == "broken"]
    for exp, r in broken:
        print(f"note: {exp}/{r['case']}/{r['run']} is broken ({r['broken']}); the report "
              "does not count it", file=sys.stderr)
    if not broken:
        return []
    return ["## Broken runs", "",
            "These runs have a metrics.json but do not read back; they count nowhere above "
            "(`mi-grg experiment` runs them again):", ""] + [
        f"- `{exp}/{r['case']}/{r['run']}`: {r['broken']}" for exp, r in broken] + [""]


#: Fields of a runs.json row the report reads, and the types they may have.
ROW_TYPES = {"case": str, "run": str, "category": (str, type(None)),
             "label": (str, type(None)), "method": (str, type(None)),
             "views": (int, type(None))}


def read_runs(path: Path):
    """The runner's index ``EXPERIMENT/runs.json`` checked ({"runs": rows, "commands":
    lines}), or None when there is none. DatasetError (naming the file and the row) for
    one that is not what the runner writes: a row's case and run must be plain names."""
    from mi_grg.data.dataset import DatasetError
    from mi_grg.data.inputs import InputError, read_json
    if not path.is_file():
        return None
    try:
        index = read_json(path, "runs.json")
    except InputError as e:
        raise DatasetError(str(e)) from None
    runs = index.get("runs", []) if isinstance(index, dict) else None
    commands = index.get("commands", []) if isinstance(index, dict) else None
    if not isinstance(runs, list) or not (isinstance(commands, list) and
                                          all(isinstance(c, str) for c in commands)):
        raise DatasetError(f"{path}: expected an object with a 'runs' list (and 'commands' "
                           "as lines of text), as mi-grg experiment writes it")
    for i, r in enumerate(runs):
        bad = ([k for k, t in ROW_TYPES.items() if not isinstance(r.get(k), t)
                or isinstance(r.get(k), bool)] if isinstance(r, dict) else ["the row"])
        if not bad and any(n in ("", ".", "..") or "/" in n or "\\" in n
                           for n in (r["case"], r["run"])):
            bad = ["case / run (a plain name)"]
        if bad:
            raise DatasetError(f"{path}: runs[{i}]: {', '.join(bad)} missing or of the wrong "
                               "type")
    return {"runs": [dict(r) for r in runs], "commands": commands}


def report_target(out: Path, report: Path, all_rows: dict, record: Path | None = None) -> Path:
    """The report's image folder, ``img/<report's name>/`` beside it (two reports in one
    folder keep their own figures), once ``mi-grg report``'s rule holds (DatasetError, one
    line, otherwise): ``out`` (or the ``record``, where ``out`` is gone) holds runs, and the
    report and its images go nowhere the runner wrote (nor into the record:
    ``mi_grg.lab.record.check_record``, before it is written)."""
    from mi_grg.data.dataset import DatasetError
    from mi_grg.data.outputs import check_report_out
    if not out.is_dir() and record is None:
        raise DatasetError(f"--out {out}: the results folder does not exist")
    if not all_rows:
        raise DatasetError(f"--out {out}: holds no runs (no EXPERIMENT/runs.json, no "
                           "EXPERIMENT/CASE/RUN/metrics.json): not a folder that `mi-grg "
                           "experiment` wrote" + (f", and the record {record} holds none"
                                                  if record is not None else ""))
    from mi_grg.lab.suite import EXPERIMENTS
    inputs = [out / "data", out / "suite.json",
              *(out / name for name in {*EXPERIMENTS, *all_rows})]
    images = report.parent / "img" / report.stem
    check_report_out(report, images, inputs, lambda head: head.startswith(REPORT_HEAD))
    return images
