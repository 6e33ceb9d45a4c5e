"""Which runs of a plan are done, shared or still to run, in a results folder.

A finished run is reused unless it is stale (``stale_options``); a run identical to a
finished one elsewhere in OUT (same data, method and options) becomes a link to it; a
trained run that differs from another of the same data and method only in what acts after
training shares that run's training (``training_twins``: it resumes from the twin's final
checkpoint and redoes only the result's steps). ``mi_grg.lab.runner`` runs the rest.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from mi_grg.lab.finished import is_finished, read_finished
from mi_grg.lab.plan import RunSpec
from mi_grg.lab.staleness import resumes, same_training, stale_keys
from mi_grg.lab.suite import TRAINED


def stale_options(run_dir: Path) -> list:
    """Training options of a finished r2/gr run whose values differ from what this code
    resolves the run's options to (a default changed since it ran); [] if none differ or
    the run is not a training run. Such a run is not reused: it is run again."""
    m = read_finished(run_dir, {})
    return [] if m is None else stale_keys(m)



def is_done(run_dir: Path) -> bool:
    return is_finished(run_dir) and not stale_options(run_dir)


def index_done(out: Path) -> dict:
    """key -> run_dir of every finished (non-symlinked) run under OUT."""
    index = {}
    for spec_file in out.glob("*/*/*/run_spec.json"):
        d = spec_file.parent
        if d.is_symlink() or not is_done(d):
            continue
        try:
            key = json.loads(spec_file.read_text())["key"]
        except (OSError, ValueError, KeyError):
            continue
        index.setdefault(key, d)
    return index


def link_run(link: Path, target: Path) -> None:
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() or link.is_file():
        link.unlink()
    elif link.exists():
        shutil.rmtree(link)   # an unfinished run replaced by an identical finished one
    os.symlink(os.path.relpath(target, link.parent), link, target_is_directory=True)


def plan_rows(specs: list, out: Path):
    """(rows, todo): a row per spec with its status (done before, linked to an identical
    finished run elsewhere, duplicate of another spec of this call, todo) and the specs to
    run."""
    index = index_done(out) if out.exists() else {}
    rows, todo, first_of = [], [], {}
    for s in specs:
        d, key = s.run_dir(out), s.key()
        row = {"experiment": s.experiment, "case": s.case.name, "run": s.run,
               "category": s.case.category, "label": s.label, "views": s.case.views,
               "method": s.method, "options": s.options, "dir": str(d)}
        if (d / "metrics.json").is_file() and not is_done(d):
            row["stale"] = stale_options(d)   # defaults changed since it ran: run again
        if is_done(d):
            row["status"] = "done before"
        elif key in index:
            row["status"], row["target"] = "linked", str(index[key])
        elif key in first_of:
            row["status"], row["target"] = "duplicate", str(first_of[key].run_dir(out))
        else:
            row["status"] = "todo"
            if (d / "checkpoint.npz").is_file():
                stale = row.get("stale") if (d / "metrics.json").is_file() else None
                row["resumes"] = resumes(s.method, s.options, d / "checkpoint.npz", stale)
            first_of[key] = s
            todo.append(s)
        rows.append(row)
    training_twins(specs, rows, index, out)
    return rows, todo


def training_twins(specs: list, rows: list, index: dict, out: Path) -> None:
    """Trained runs to do that differ from another run of the same data and method only in
    what acts after training (``same_training``: gr-paper beside gr) get ``trains_with``:
    the twin's folder. A finished twin's final checkpoint is copied in before the run
    starts; a twin run in this call runs first, and the run then resumes from its
    checkpoint, redoing only the result's steps instead of training again."""
    finished = []
    for k, d in index.items():
        try:
            finished.append((json.loads(k), d))
        except ValueError:
            continue
    trainers = []            # (spec) runs of this call that train (or resume) their own state
    for s, row in zip(specs, rows):
        if row["status"] != "todo" or s.method not in TRAINED:
            continue
        if row.get("resumes"):   # its own checkpoint: it may lend it once it has run
            trainers.append(s)
            continue
        case = json.loads(s.key())["case"]
        twin = next((d for k, d in finished
                     if k.get("case") == case and k.get("method") == s.method
                     and Path(d) != s.run_dir(out)
                     and (Path(d) / "checkpoint.npz").is_file()
                     and same_training(s.method, s.options, k.get("options") or {})), None)
        if twin is None:
            twin = next((t.run_dir(out) for t in trainers
                         if t.case.key() == s.case.key() and t.method == s.method
                         and same_training(s.method, s.options, t.options)), None)
            if twin is not None:
                row["waits"] = True
        if twin is None:
            trainers.append(s)
        else:
            row["trains_with"] = str(twin)


def take_twin_checkpoint(spec: RunSpec, row: dict, out: Path) -> None:
    """Copy the final checkpoint of the run that ``row`` trains with into the run's folder,
    where it still resumes under the run's options; otherwise the run trains afresh."""
    src = Path(row["trains_with"]) / "checkpoint.npz"
    if src.is_file() and resumes(spec.method, spec.options, src, None):
        shutil.copyfile(src, spec.run_dir(out) / "checkpoint.npz")
    else:
        row["trains_with"] = None


def write_specs(todo: list, rows: list, out: Path) -> None:
    """Each run's run_spec.json, before any runs: a run in progress is recognisable on disk.
    A run starts afresh (its metrics.json and checkpoint gone) unless its row ``resumes``
    (``mi_grg.lab.staleness.resumes``): then its checkpoint stays and the run continues from it."""
    resume = {r["dir"] for r in rows if r.get("resumes")}
    for s in todo:
        d = s.run_dir(out)
        if d.is_symlink():            # linked to a run that is stale now: run it here
            d.unlink()
        if str(d) not in resume:
            (d / "checkpoint.npz").unlink(missing_ok=True)
        (d / "metrics.json").unlink(missing_ok=True)
        d.mkdir(parents=True, exist_ok=True)
        (d / "run_spec.json").write_text(json.dumps({**s.to_dict(), "key": s.key()},
                                                    indent=2, default=str))


def resolve_duplicates(specs: list, rows: list, out: Path) -> None:
    """Linked and duplicate runs become links to their finished twin, or failures."""
    for s, row in zip(specs, rows):
        if row["status"] in ("linked", "duplicate"):
            target = Path(row["target"])
            if is_done(target):
                link_run(s.run_dir(out), target)
                row["status"] = "linked"
            else:
                row["status"] = "failed"
                row["error"] = f"identical run {target} failed"
