"""Experiment runs on a Dask distributed cluster (``mi-grg experiment ... --dask ADDRESS``).

The submitting process plans the runs, writes their run_spec.json and every runs.json; the
cluster only executes tasks, one per data set to simulate and then one per run, each
writing its results into OUT (a file system that the workers share with the submitter).

A worker runs one task at a time (``_ONE_RUN``): a run sets process-wide state (the
Mitsuba variant, Dr.Jit's thread count, stdout redirected into its log.txt), so two runs in
threads of one worker process would disturb each other. Workers are therefore best started
with ``--nthreads 1`` and as many processes per machine (``--nworkers``) as its cores allow
for the runs' ``--threads-per-run``.

When a worker dies (crash, OOM kill, lost node), the scheduler runs its task elsewhere.
Each task counts its starts in a file in OUT (``attempts_file``): a task is started at most
``MAX_STARTS`` times (resubmitted at most twice); a further start, or the scheduler giving
up first (``distributed.scheduler.allowed-failures``, default 3, raises ``KilledWorker``),
records the run as failed with the reason.
"""
from __future__ import annotations

import os
import socket
import threading
import time
import uuid
from pathlib import Path

MAX_STARTS = 3          # the first start and at most two resubmissions after a worker died
CONNECT_TIMEOUT = 3.0   # seconds to reach the scheduler before giving up

_ONE_RUN = threading.Lock()


def connect(address: str, timeout: float = CONNECT_TIMEOUT):
    """A ``distributed.Client`` on the scheduler at ``address`` (``tcp://host:8786``), or a
    ValueError naming the address and the error, within about twice ``timeout``."""
    def unreachable(e):
        return ValueError(f"cannot reach the Dask scheduler at {address}: "
                          f"{type(e).__name__}: {e}")
    # A plain TCP connection first: a refused port or an unknown host fails at once, where
    # Dask would retry for its whole connect timeout.
    scheme, sep, location = address.rpartition("://")
    if scheme in ("tcp", "tls") or not sep:
        host, _, port = location.rpartition(":") if ":" in location else (location, "", "")
        try:
            socket.create_connection((host.strip("[]"), int(port or 8786)),
                                     timeout=timeout).close()
        except (OSError, ValueError) as e:
            raise unreachable(e) from None
    # Then one request in Dask's protocol: a port that answers something else fails here
    # (a Client would hang while closing itself after such a failure).
    import asyncio
    from concurrent.futures import ThreadPoolExecutor
    from distributed.core import rpc

    async def identity():
        scheduler = rpc(address, timeout=timeout)
        try:
            return await asyncio.wait_for(scheduler.identity(), timeout)
        finally:
            await scheduler.close_rpc()

    try:   # in a thread of its own: the caller may be inside an event loop (Jupyter)
        with ThreadPoolExecutor(1) as pool:
            pool.submit(asyncio.run, identity()).result()
    except Exception as e:  # noqa: BLE001 (OSError, TimeoutError, garbage from a wrong port)
        raise unreachable(e) from None
    from distributed import Client
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except Exception as e:  # noqa: BLE001
        raise unreachable(e) from None


def run_on_cluster(client, func, tasks: list, desc: str):
    """Submit ``func(task)`` for every task (each with an ``attempts_file``), longest first
    as given; yield (i, result) as they finish. A task the cluster cannot finish yields a
    failed result naming why."""
    from distributed import as_completed
    tag = uuid.uuid4().hex[:8]
    futures = {}
    for i, task in enumerate(tasks):
        Path(task["attempts_file"]).unlink(missing_ok=True)   # a fresh count per invocation
        fut = client.submit(_counted, func, task, key=f"mi_grg-{desc}-{i}-{tag}", pure=False,
                            priority=len(tasks) - i)
        futures[fut] = i
    try:
        for fut in as_completed(futures, loop=client.loop):
            try:
                res = fut.result()
            except Exception as e:  # noqa: BLE001 (KilledWorker, a task that cannot unpickle)
                res = {"status": "failed", "error": f"{type(e).__name__}: {e}"}
            yield futures[fut], res
    finally:
        client.cancel(list(futures))     # nothing stays queued when the submitter stops


def _counted(func, task: dict) -> dict:
    """Worker side: ``func(task)``, one at a time per worker process, started at most
    ``MAX_STARTS`` times (the starts are lines of the task's attempts file)."""
    marker = Path(task["attempts_file"])
    with _ONE_RUN:
        starts = marker.read_text().splitlines() if marker.is_file() else []
        if len(starts) >= MAX_STARTS:
            return {"status": "failed",
                    "error": f"its worker died {len(starts)} times while running it "
                             f"({'; '.join(starts)}); not resubmitted again"}
        marker.parent.mkdir(parents=True, exist_ok=True)
        with open(marker, "a") as f:
            f.write(f"{socket.gethostname()} pid {os.getpid()} at "
                    f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        result = func(task)
        marker.unlink(missing_ok=True)
        return result
