"""`mi-grg reconstruct` replaces an earlier output only whole and only once the new one is
complete: a run that fails, is interrupted or is killed leaves the earlier output byte for
byte, a stale temporary is cleaned (and named) by the next run, and --resume continues an
interrupted or killed run from the checkpoint in its temporary."""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_grg.cli import main

#: A gr run of a few seconds; checkpoint_every=5 so that a kill soon finds a checkpoint.
GR = ["--method", "gr", "--option", "n_points=300", "--option", "progress=false",
      "--option", "holdout_every=3", "--option", "checkpoint_every=5"]
SART = ["--method", "sart", "--option", "n_iter=2", "--option", "stop=none"]
RUN_FILES = {"metrics.json", "slices.png", "vol_pred.npy", "vol_pred.tif"}
GR_FILES = RUN_FILES | {"checkpoint.npz", "gaussians.npz", "gaussians.ply", "train_log.csv",
                        "train_log.png"}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """data/: a tiny simulated case; run/: an earlier fdk run of it, the output that the
    tests replace."""
    root = tmp_path_factory.mktemp("atomic")
    assert main(["simulate", "--phantom", "shepp", "--n", "16", "--det", "16", "--views", "6",
                 "--test-views", "2", "--out", str(root / "data")]) == 0
    assert main(["reconstruct", str(root / "data"), "--method", "fdk",
                 "--out", str(root / "run")]) == 0
    return root


def hidden(root: Path) -> list:
    return sorted(p.name for p in root.iterdir() if p.name.startswith("."))


def reconstruct(root: Path, capsys, *argv) -> tuple:
    """(exit status, stderr) of `mi-grg reconstruct root/data ARGV --out root/run`."""
    rc = main(["reconstruct", str(root / "data"), *argv, "--out", str(root / "run")])
    return rc, capsys.readouterr().err.strip()


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def gr_metrics(root: Path) -> dict:
    return json.loads((root / "run" / "metrics.json").read_text())


# ---------------------------------------------------------------- failures
def test_a_failed_write_leaves_the_earlier_output(root, capsys, monkeypatch, tree_hash):
    """The new output is written, then the disk is full: --out is the earlier run, byte
    for byte, and nothing temporary is left beside it."""
    import mi_grg.methods as methods
    real = methods.write_outputs

    def full_disk(out_dir, *a, **k):
        real(out_dir, *a, **k)
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(out_dir) / "x"))
    monkeypatch.setattr(methods, "write_outputs", full_disk)
    before = tree_hash(root)
    rc, err = reconstruct(root, capsys, *SART)
    last = err.splitlines()[-1]     # (SART's progress bar is above)
    assert rc == 2 and last.startswith("mi-grg reconstruct: error: "), err
    assert "No space left on device" in last
    assert hidden(root) == []
    assert tree_hash(root) == before


def test_a_training_run_that_fails_leaves_the_earlier_output(root, capsys, monkeypatch, tree_hash):
    """gr fails at its second checkpoint, after the first was written: the earlier output
    is untouched and the failed run's temporary (checkpoint included) is gone."""
    from mi_grg.training.trainer import Trainer
    real, calls = Trainer._save_checkpoint, []

    def failing(self):
        calls.append(self.state.iteration)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.checkpoint_path))
        real(self)
    monkeypatch.setattr(Trainer, "_save_checkpoint", failing)
    before = tree_hash(root)
    rc, err = reconstruct(root, capsys, *GR, "--option", "iterations=20")
    assert calls == [5, 10]
    assert rc == 2 and "No space left on device" in err, err
    assert hidden(root) == []
    assert tree_hash(root) == before


# ---------------------------------------------------------------- stale temporaries
def test_stale_temporaries_are_cleaned_and_named(root, capsys):
    """A killed run's temporary and an interrupted run's kept one (dead processes) are
    removed by the next run, which says so; a live process's temporary is left alone."""
    pid = dead_pid()
    for name in (f".run.reconstruct-{pid}", f".run.partial-{pid}"):
        (root / name).mkdir()
        (root / name / "checkpoint.npz").write_bytes(b"a stopped run's checkpoint")
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (root / f".run.reconstruct-{live.pid}").mkdir()
        rc, err = reconstruct(root, capsys, *SART)
    finally:
        live.kill()
        live.wait()
    assert rc == 0, err
    assert f"removed .run.reconstruct-{pid}, left by a killed run" in err
    assert f"removed .run.partial-{pid}" in err and "--resume" in err
    assert hidden(root) == [f".run.reconstruct-{live.pid}"]
    assert gr_metrics(root)["method"] == "sart"


def test_resume_finds_the_newest_checkpoint_of_a_stopped_run(tmp_path):
    """Of the temporaries beside --out, those of ended processes count (not a running
    one's, not an old output set aside), and the newest checkpoint among them wins."""
    from mi_grg.data.outputs import resumable
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        names = [f".run.reconstruct-{dead_pid()}", f".run.partial-{dead_pid()}",
                 f".run.old-{dead_pid()}", f".run.reconstruct-{live.pid}"]
        for age, name in zip((30, 20, 10, 0), names):
            (tmp_path / name).mkdir()
            (tmp_path / name / "checkpoint.npz").write_bytes(b"x")
            os.utime(tmp_path / name / "checkpoint.npz", (time.time() - age,) * 2)
        assert resumable(tmp_path / "run", "reconstruct", "checkpoint.npz") == \
            tmp_path / names[1] / "checkpoint.npz"
    finally:
        live.kill()
        live.wait()
    assert resumable(tmp_path / "other", "reconstruct", "checkpoint.npz") is None


def test_the_replaced_output_is_whole_and_complete(root, capsys):
    """Not a merge: a file of the earlier output that the new run does not write is gone,
    and every file of the new one is there and consistent."""
    (root / "run" / "checkpoint.npz").write_bytes(b"from an earlier gr run")
    old = np.load(root / "run" / "vol_pred.npy")
    rc, err = reconstruct(root, capsys, *SART)
    assert rc == 0, err
    assert {p.name for p in (root / "run").iterdir()} == RUN_FILES
    metrics = gr_metrics(root)
    assert metrics["method"] == "sart" and metrics["options"]["n_iter"] == 2
    new = np.load(root / "run" / "vol_pred.npy")
    assert new.shape == old.shape and not np.array_equal(new, old)
    assert hidden(root) == []


# ---------------------------------------------------------------- interrupted, killed
def test_ctrl_c_keeps_the_run_for_resume(root, capsys, monkeypatch, sigint_raises, tree_hash):
    """Ctrl-C at iteration 7: exit 130, --out unchanged, the run kept beside it with its
    checkpoint of iteration 7; a resume with other options fails and keeps it; a resume
    interrupted again at 12 keeps the newer run only; the same command with --resume then
    continues from 12 to the end, and nothing temporary is left."""
    from mi_grg.training.trainer import Trainer
    step, stops = Trainer._step, [7, 12]

    def ctrl_c(self, it, raw):
        if stops and it == stops[0]:
            stops.pop(0)
            os.kill(os.getpid(), signal.SIGINT)
        return step(self, it, raw)
    monkeypatch.setattr(Trainer, "_step", ctrl_c)
    gr = [*GR, "--option", "iterations=20"]
    before = tree_hash(root / "run")
    rc, err = reconstruct(root, capsys, *gr)
    kept = root / f".run.partial-{os.getpid()}"
    assert rc == 130 and "--resume" in err, err
    assert tree_hash(root / "run") == before and hidden(root) == [kept.name]
    rc, err = reconstruct(root, capsys, *gr, "--option", "lambda_tv=0.5", "--resume")
    assert rc == 2 and "lambda_tv" in err, err
    assert hidden(root) == [kept.name] and tree_hash(root / "run") == before
    # as if a process that has ended had kept it
    earlier = root / f".run.partial-{dead_pid()}"
    kept.rename(earlier)
    rc, err = reconstruct(root, capsys, *gr, "--resume")
    assert rc == 130 and f"resuming from {earlier}" in err, err
    assert tree_hash(root / "run") == before and hidden(root) == [kept.name]
    rc, err = reconstruct(root, capsys, *gr, "--resume")
    assert rc == 0, err
    info = gr_metrics(root)["method_info"]
    assert info["init"] == {"resumed_from": 12} and info["iterations_run"] == 20
    assert {p.name for p in (root / "run").iterdir()} == GR_FILES
    assert hidden(root) == []


def test_a_killed_run_resumes(root, capsys, tree_hash):
    """A real process replacing the earlier output is killed (SIGKILL) once it has a
    checkpoint: --out is the earlier run byte for byte, and the same command with --resume
    continues from the killed run's checkpoint to the end and replaces --out whole."""
    gr = [*GR, "--option", "iterations=60"]
    (root / "run" / "notes.txt").write_text("only in the earlier output")
    before = tree_hash(root / "run")
    p = subprocess.Popen([sys.executable, "-m", "mi_grg.cli", "reconstruct",
                          str(root / "data"), *gr, "--out", str(root / "run")],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    staged = root / f".run.reconstruct-{p.pid}" / "checkpoint.npz"
    deadline = time.monotonic() + 120
    while not staged.exists() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    p.kill()
    _, err = p.communicate()
    assert p.returncode == -signal.SIGKILL, err.decode()
    assert tree_hash(root / "run") == before
    assert hidden(root) == [staged.parent.name]
    rc, err = reconstruct(root, capsys, *gr, "--resume")
    assert rc == 0, err
    assert f"resuming from {staged}" in err
    info = gr_metrics(root)["method_info"]
    start = info["init"]["resumed_from"]
    assert start > 0 and start % 5 == 0 and info["iterations_run"] == 60
    assert {p.name for p in (root / "run").iterdir()} == GR_FILES
    assert gr_metrics(root)["options"]["out_dir"] == str(root / "run")
    assert hidden(root) == []
