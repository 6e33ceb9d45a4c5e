"""Where a command writes: never onto its inputs, and an old output replaced atomically.

One rule for every command's ``--out`` (``check_out``): it may not be, hold or lie inside
an input (the scan and its flats / darks folders, the data set, a run, a scene file), and
a non-empty ``--out`` must be an earlier output of the same command (``Output``: the files
that mark one), which is then replaced whole; stale temporaries of killed runs are
repaired first (``clean_stale``).

One staged write (``staged``): the new output is built in a hidden temporary directory
beside ``--out`` and swapped in at the end: a failure (or a kill) before the swap leaves
the old output as it was; the swap is two renames, and ``clean_stale`` repairs a kill
between them on the next run (the old output is put back, temporaries of dead processes
are removed). A full disk is named as such: the file being written and the space left.

A run that can be resumed (``Output.resumable``: the name of its checkpoint) keeps its
temporary when interrupted (Ctrl-C) as ``.OUT.partial-PID``; ``resumable`` finds the
checkpoint of such a run, or of one killed while writing into its temporary, for the next
run to continue. ``staged_report`` does the same for a report file and its image folder.
"""
from __future__ import annotations

import contextlib
import errno
import glob as _glob
import os
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from mi_grg.data.dataset import META_NAME, DatasetError


@dataclass(frozen=True)
class Output:
    """What one command writes into ``--out``: ``tag`` (in its temporaries' names), the
    files that make a folder an earlier output of it (``markers``: all of them, or any one
    with ``any_marker``) and those that make it another command's (``foreign``), how to
    name such a folder (``what``) and, for a run that can be continued, the name of its
    checkpoint (``resumable``)."""
    tag: str
    markers: tuple
    what: str
    any_marker: bool = False
    foreign: tuple = ()
    resumable: str | None = None

    def marks(self, folder: Path) -> bool:
        if any((folder / f).exists() for f in self.foreign):
            return False
        found = [(folder / m).is_file() for m in self.markers]
        return any(found) if self.any_marker else all(found)


#: An imported scan is never replaced by a simulation.
SIMULATE = Output("simulate", (META_NAME,), "a simulated data set", foreign=("import.json",))
IMPORT = Output("import", (META_NAME,), "a data set")
#: A run that stopped has only its checkpoint; a finished one its metrics.json.
RECONSTRUCT = Output("reconstruct", ("metrics.json", "checkpoint.npz"), "an earlier run",
                     any_marker=True, resumable="checkpoint.npz")
RENDER = Output("render", ("crosscheck.json",), "an earlier mi-grg render output")
PREVIEW = Output("preview", ("preview.png", "preview.gif"), "an earlier preview")


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


def check_replaceable(out, kind: Output, overwrite: bool = True,
                      option: str = "--out") -> None:
    """DatasetError unless a non-empty ``out`` may be replaced: ``overwrite`` given, ``out``
    an earlier output of the command ``kind`` (an unrelated folder, an input, a data set
    given to a command that does not write data sets, is never deleted), and every folder
    in it writable, so that the old output can be removed after the swap."""
    out = Path(out)
    if not (out.is_dir() and any(out.iterdir())):
        return
    if not overwrite:
        raise DatasetError(f"{option} {out}: exists and is not empty (use --overwrite)")
    if not kind.marks(out):
        join = " or " if kind.any_marker else " and "
        found = [f for f in kind.foreign if (out / f).exists()]
        why = (f"it has {', '.join(found)}" if found else f"no {join.join(kind.markers)}")
        raise DatasetError(f"{option} {out}: not {kind.what} ({why}), and only an earlier "
                           "output is ever replaced; give a new directory")
    for folder in [out, *(p for p in out.rglob("*") if p.is_dir() and not p.is_symlink())]:
        if not os.access(folder, os.W_OK | os.X_OK):
            raise DatasetError(f"{option} {out}: {folder} is not writable, so the old "
                               "output could not be removed")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise DatasetError(f"{option} {out}: {out.parent} is not writable")


def check_out(out, kind: Output, inputs=(), overwrite: bool = True, keep=(),
              option: str = "--out") -> None:
    """The one rule for every command's ``--out``, checked before any work: writable; not,
    not holding and not inside any of ``inputs`` (files and folders: the scan and its
    flats / darks folders, the data set, a run, a scene); what killed runs left beside it
    repaired (except the temporaries in ``keep``: one being resumed); and new, empty or an
    earlier output of ``kind`` (``check_replaceable``)."""
    check_writable(out, option)
    check_apart(out, [p for p in inputs if p is not None], option)
    for note in clean_stale(out, kind.tag, keep):
        print(f"note: {note}", file=sys.stderr)
    check_replaceable(out, kind, overwrite, option)


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
                shutil.rmtree(path) if path.is_dir() else path.unlink()
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
    except OSError as e:
        full = _disk_full(e, tmp, out)
        shutil.rmtree(tmp, ignore_errors=True)
        if full is not None:
            raise full from e
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} TiB"


def _disk_full(e: OSError, tmp: Path, out: Path):
    """For a full disk while writing into ``tmp`` (ENOSPC, or NumPy's "N requested and M
    written"), an OSError naming the file as it would be in ``out`` and the space left;
    None for any other error."""
    if e.errno != errno.ENOSPC and not (
            e.errno is None and re.search(r"\d+ requested and \d+ written", str(e))):
        return None
    files = [p for p in tmp.rglob("*") if p.is_file()] if tmp.is_dir() else []
    path = Path(e.filename) if e.filename else max(
        files, key=lambda p: p.stat().st_mtime_ns, default=None)
    shown = out if path is None else (out / path.relative_to(tmp)
                                      if tmp == path or tmp in path.parents else path)
    where = out.parent
    while not where.exists():
        where = where.parent
    free = shutil.disk_usage(where).free
    return OSError(errno.ENOSPC, f"No space left on device while writing it ({_bytes(free)} "
                   f"free on the file system of {where})", str(shown))


def resume_source(out, kind: Output):
    """The checkpoint that a stopped run of ``kind`` left in a temporary beside ``out``
    (the newest), or None."""
    return resumable(out, kind.tag, kind.resumable) if kind.resumable else None


@contextlib.contextmanager
def staged(out, kind: Output, resumed=None):
    """``replaced_dir`` for a command ``kind``: yields the temporary to write into. An
    interrupted run of a resumable kind is kept for --resume. ``resumed``: the checkpoint
    (from ``resume_source``) this run continues; its temporary is kept while the run goes
    on and removed once the run is done, or once an interruption kept a newer checkpoint."""
    consumed = Path(resumed).parent if resumed is not None else None
    try:
        with replaced_dir(out, kind.tag, keep=[consumed] if consumed else [],
                          partial=kind.resumable) as tmp:
            yield tmp
    except KeyboardInterrupt:
        newer = partial_dir(out) / str(kind.resumable)
        if (consumed is not None and consumed != newer.parent and newer.is_file()
                and newer.stat().st_mtime_ns > Path(resumed).stat().st_mtime_ns):
            shutil.rmtree(consumed, ignore_errors=True)
        raise
    if consumed is not None:
        shutil.rmtree(consumed, ignore_errors=True)


@contextlib.contextmanager
def staged_reconstruct(out, inputs, resume: bool = False):
    """``staged`` for ``mi-grg reconstruct``: checks ``out`` against ``inputs`` (the data
    set, the config file) and yields (the temporary to write the run into, the checkpoint
    to resume from or None). With ``resume`` the run continues the one that stopped (its
    temporary's checkpoint, said on stderr), else ``out``'s own checkpoint."""
    source = resume_source(out, RECONSTRUCT) if resume else None
    check_out(out, RECONSTRUCT, inputs, keep=[source.parent] if source else [])
    checkpoint = None
    if resume:
        if source is not None:
            print(f"note: resuming from {source}, left by a run that stopped", file=sys.stderr)
        checkpoint = str(source if source is not None else Path(out) / RECONSTRUCT.resumable)
    with staged(out, RECONSTRUCT, resumed=source) as tmp:
        yield tmp, checkpoint


def check_report_out(report, images, inputs, is_report, option: str = "--report") -> None:
    """A report file and its image folder may not be, hold or lie inside any of ``inputs``
    (what the runner wrote); an existing report file must be an earlier report
    (``is_report(its first line)``) and an existing image folder hold only PNG images."""
    report, images = Path(report), Path(images)
    for target in (report, images):
        check_apart(target, inputs, option)
    check_writable(report.parent, option)
    if report.is_dir():
        raise DatasetError(f"{option} {report}: is a directory; expected a markdown file")
    if report.exists():
        with open(report, "rb") as f:
            head = f.readline(200).decode("utf-8", "replace")
        if not is_report(head):
            raise DatasetError(f"{option} {report}: exists and is not an earlier report (it "
                               f"starts {head.strip()[:60]!r}); give a new file")
    if images.exists():
        other = ([images] if not images.is_dir() else
                 [p for p in images.iterdir() if p.suffix != ".png" or not p.is_file()])
        if other:
            raise DatasetError(f"{option} {report}: its image folder {images} holds "
                               f"{other[0].name}, which no report wrote; give a report in "
                               "another folder")


@contextlib.contextmanager
def staged_report(report, images):
    """Yield (temporary report file, temporary image folder) beside them; when the block
    succeeds the image folder is swapped in whole and then the report file replaced, else
    both are left as they were."""
    report = Path(report)
    report.parent.mkdir(parents=True, exist_ok=True)
    Path(images).parent.mkdir(parents=True, exist_ok=True)
    for note in clean_stale(report, "report"):
        print(f"note: {note}", file=sys.stderr)
    tmp = report.parent / f".{report.name}.report-{os.getpid()}"
    try:
        with replaced_dir(images, "report") as tmp_images:
            tmp_images.mkdir()
            yield tmp, tmp_images
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, report)


@contextlib.contextmanager
def staged_files(folder, names, tag: str):
    """Yield a temporary directory beside ``folder``; when the block succeeds each file of
    ``names`` written there replaces its namesake in ``folder`` (one rename each: a file is
    never seen half-written), else nothing in ``folder`` changes. Temporaries of ``tag``
    that dead processes left are removed first (only those: a stopped run's are kept)."""
    folder = Path(folder)
    for kind, pid, path in _temporaries(folder, tag):
        if kind == tag and not _alive(pid):
            shutil.rmtree(path, ignore_errors=True)
    tmp = folder.parent / f".{folder.name}.{tag}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        for name in names:
            os.replace(tmp / name, folder / name)
    except OSError as e:
        full = _disk_full(e, tmp, folder)
        if full is not None:
            raise full from e
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
