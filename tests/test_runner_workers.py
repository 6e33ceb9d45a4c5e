"""The experiment runner's processes: its local workers stop when the runner is killed (a
worker left running would go on writing its run folder beside the next runner that resumes
it), and one runner at a time writes an --out."""
import os
import socket
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    """Running (a zombie that nobody reaped has stopped)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in state


def _wait(cond, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.2)
    return cond()


def test_a_killed_runner_takes_its_workers_with_it(tmp_path):
    (tmp_path / "slow_task.py").write_text(textwrap.dedent("""
        import os, time
        def run(task):
            open(task["pid_file"], "w").write(str(os.getpid()))
            time.sleep(120)
            return {"status": "ok"}
    """))
    pid_file = tmp_path / "worker.pid"
    runner = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys
            sys.path.insert(0, {str(tmp_path)!r})
            import slow_task
            from mi_grg.lab.runner import _run_local
            for _ in _run_local(slow_task.run, [{{"pid_file": {str(pid_file)!r}}}], 1):
                pass
        """)], cwd=tmp_path)
    worker = None
    try:
        assert _wait(lambda: pid_file.is_file() and pid_file.read_text(), 120), \
            "the worker never started"
        worker = int(pid_file.read_text())
        assert _alive(worker)
        runner.send_signal(signal.SIGTERM)          # the runner alone, as `kill PID` does
        runner.wait(timeout=30)
        assert _wait(lambda: not _alive(worker), 15), \
            f"worker {worker} still runs after its runner was killed"
    finally:
        if runner.poll() is None:
            runner.kill()
        if worker is not None and _alive(worker):
            os.kill(worker, signal.SIGKILL)


def test_one_runner_at_a_time(tmp_path):
    from mi_grg.lab.runner import RUNNER_FILE, _one_runner, run_experiment
    out, host = tmp_path / "results", socket.gethostname()
    out.mkdir()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / RUNNER_FILE).write_text(f"{host} {other.pid}")
        with pytest.raises(ValueError, match=rf"another `mi-grg experiment` \(pid {other.pid}"):
            run_experiment("table1", ROOT / "experiments" / "suite_smoke.json", out,
                           methods="fdk", progress=False)
        assert not (out / "suite.json").exists()        # refused before writing anything
    finally:
        other.kill()
        other.wait()
    # a runner that died is taken over; the file goes when the runner ends
    with _one_runner(out):
        assert (out / RUNNER_FILE).read_text() == f"{host} {os.getpid()}"
        with pytest.raises(ValueError, match=f"pid {os.getpid()}"):
            with _one_runner(out):
                pass
    assert not (out / RUNNER_FILE).exists()
    # one on another host cannot be checked from here: refused, with the file named
    (out / RUNNER_FILE).write_text("elsewhere 12345")
    with pytest.raises(ValueError, match="remove .*runner.pid"):
        with _one_runner(out):
            pass
