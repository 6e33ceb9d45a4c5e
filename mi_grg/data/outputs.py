"""Where a command writes: never onto its inputs, and an old output replaced atomically.

``check_apart`` refuses an output directory that is, contains or lies inside an input.
``replaced_dir`` writes a new output into a hidden temporary directory beside it and swaps
it in at the end: a failure (or a kill) before the swap leaves the old output as it was; the
swap is two renames, and ``clean_stale`` repairs a kill between them on the next run
(the old output is put back, temporaries of dead processes are removed).

A run that can be resumed (``partial``: the name of its checkpoint) keeps its temporary when
interrupted (Ctrl-C) as ``.OUT.partial-PID``; ``resumable`` finds the checkpoint of such a
run, or of one killed while writing into its temporary, for the next run to continue.
"""
from __future__ import annotations

import contextlib
import glob as _glob
import os
import re
import shutil
import sys
from pathlib import Path

from mi_grg.data.dataset import META_NAME, DatasetError


def input_paths(pattern) -> list:
    """The files a path or glob pattern names (the pattern itself when nothing matches)."""
    if pattern is None:
        return []
    matches = _glob.glob(str(pattern))
    return [Path(p) for p in matches] if matches else [Path(pattern)]


def check_apart(out, inputs, option: str = "--out") -> None:
    """DatasetError when ``out`` is, contains or lies inside one of ``inputs``: writing
    there could delete or change the input."""
    target = Path(out).resolve()
    for p in inputs:
        src = Path(p).resolve()
        if src == target or target in src.parents:
            how = "is" if src == target else "holds"
            raise DatasetError(f"{option} {out}: {how} the input {p}; give an {option} "
                               "directory apart from the inputs")
        if src in target.parents:
            raise DatasetError(f"{option} {out}: lies inside the input {p}; give an "
                               f"{option} directory apart from the inputs")


def check_writable(out, option: str = "--out") -> None:
    """DatasetError unless ``out`` can be created or written: it is a directory (or does
    not exist yet) and its nearest existing ancestor is a writable directory."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{option} {out}: is a file; expected a directory")
    parent = out if out.exists() else out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise DatasetError(f"{option} {out}: {parent} is a file; expected a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise DatasetError(f"{option} {out}: {parent} is not writable")


def check_replaceable(out, overwrite: bool, option: str = "--out",
                      markers: tuple = (META_NAME,), what: str = "a data set") -> None:
    """DatasetError unless a non-empty ``out`` may be replaced: ``overwrite`` given, ``out``
    an earlier output (it has one of the files ``markers``: an unrelated folder is never
    deleted), and every folder in it writable, so that the old output can be removed after
    the swap."""
    out = Path(out)
    if not (out.is_dir() and any(out.iterdir())):
        return
    if not overwrite:
        raise DatasetError(f"{option} {out}: exists and is not empty (use --overwrite)")
    if not any((out / m).is_file() for m in markers):
        raise DatasetError(f"{option} {out}: not {what} (no {' or '.join(markers)}), and only "
                           "an earlier output is ever replaced; give a new directory")
    for folder in [out, *(p for p in out.rglob("*") if p.is_dir() and not p.is_symlink())]:
        if not os.access(folder, os.W_OK | os.X_OK):
            raise DatasetError(f"{option} {out}: {folder} is not writable, so the old "
                               "output could not be removed")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise DatasetError(f"{option} {out}: {out.parent} is not writable")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _temporaries(out: Path, tag: str) -> list:
    """(kind, pid, path) of the hidden temporaries beside ``out``."""
    pattern = re.compile(rf"\.{re.escape(out.name)}\.({re.escape(tag)}|old|partial)-(\d+)")
    found = []
    for p in out.parent.glob(f".{_glob.escape(out.name)}.*-*"):
        m = pattern.fullmatch(p.name)
        if m:
            found.append((m.group(1), int(m.group(2)), p))
    return found


def _stale(out: Path, tag: str) -> list:
    """The temporaries beside ``out`` that no running process writes: a dead one's, and an
    interrupted run's of this process (it is finished)."""
    return [t for t in _temporaries(out, tag)
            if (t[1] != os.getpid() and not _alive(t[1]))
            or (t[0] == "partial" and t[1] == os.getpid())]


def partial_dir(out) -> Path:
    """Where this process keeps an interrupted run's temporary (``replaced_dir``)."""
    out = Path(out)
    return out.parent / f".{out.name}.partial-{os.getpid()}"


def resumable(out, tag: str, name: str):
    """The newest file ``name`` (a checkpoint) in a temporary beside ``out`` that a killed
    or interrupted run left, or None."""
    out = Path(out)
    if not out.parent.is_dir():
        return None
    found = [path / name for kind, _, path in _stale(out, tag)
             if kind != "old" and (path / name).is_file()]
    return max(found, key=lambda p: p.stat().st_mtime_ns, default=None)


def clean_stale(out, tag: str, keep=()) -> list:
    """Repair what a killed run left beside ``out``: its old output is put back when the
    swap did not finish, its temporaries are removed (except those in ``keep``). Returns one
    note per repair."""
    out = Path(out)
    notes = []
    if not out.parent.is_dir():
        return notes
    keep = {Path(k) for k in keep}
    stale = [t for t in _stale(out, tag) if t[2] not in keep]
    for kind, pid, path in sorted(stale, key=lambda t: t[0] != "old"):
        if kind == "old" and not out.exists():
            os.rename(path, out)
            notes.append(f"restored {out} from {path.name} (a run, pid {pid}, was killed "
                         "while replacing it)")
        else:
            try:
                shutil.rmtree(path)
            except OSError as e:   # named, but it must not block this run
                notes.append(f"{path} is left by a run (pid {pid}) and cannot be removed "
                             f"({e}); remove it by hand")
                continue
            notes.append(f"removed {path.name}, left by a killed run (pid {pid})"
                         if kind != "partial" else
                         f"removed {path.name}, the checkpoint of an interrupted run (pid "
                         f"{pid}) that this run does not resume (--resume would)")
    return notes


def _swap(tmp: Path, out: Path) -> None:
    """Move ``tmp`` to ``out``; an existing ``out`` is renamed aside first, put back when
    the second rename fails, and removed once the new output is in place."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    try:
        shutil.rmtree(old)
    except OSError as e:   # the new output is complete; say what is left, do not fail
        print(f"warning: {out} replaced, but its previous version is left at {old} ({e})",
              file=sys.stderr)


def _keep_partial(tmp: Path, out: Path) -> None:
    """Keep an interrupted run's temporary for --resume (an earlier one of this process is
    superseded), and say where it is."""
    kept = partial_dir(out)
    if kept.exists():
        shutil.rmtree(kept)
    os.rename(tmp, kept)
    print(f"note: {out} is unchanged; the interrupted run is kept in {kept} (the same "
          "command with --resume continues it)", file=sys.stderr)


@contextlib.contextmanager
def replaced_dir(out, tag: str, keep=(), partial: str | None = None):
    """Yield a fresh temporary directory beside ``out``; when the block succeeds it
    becomes ``out`` (replacing an old one), otherwise it is removed and ``out`` is left
    as it was. Stale temporaries are cleaned first, except those in ``keep``; with
    ``partial`` (a checkpoint's name), an interrupted block (KeyboardInterrupt) whose
    temporary holds that file keeps it as ``partial_dir(out)``."""
    out = Path(out)
    for note in clean_stale(out, tag, keep):
        print(f"note: {note}", file=sys.stderr)
    tmp = out.parent / f".{out.name}.{tag}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        yield tmp
        _swap(tmp, out)
    except KeyboardInterrupt:
        if partial is not None and (tmp / partial).is_file():
            _keep_partial(tmp, out)
        else:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
