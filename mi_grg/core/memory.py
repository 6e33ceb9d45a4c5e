"""Memory estimates, checked before anything large is allocated.

Each command states what it is about to allocate as a list of ``Need`` records, one per
kind of allocation (``volume``, ``projections``, ``gaussians``, ``plans``, ``film``), and
``check`` refuses the whole list in one line when

* one array would hold ``MAX_ENTRIES`` entries or more (Dr.Jit indexes with 32-bit
  integers, so such an array cannot be built: it would crash, not fail), or
* the sum is above the limit: the machine's available memory, or ``--max-memory`` GiB
  when given (``set_max_memory``; the environment variable carries it into the worker
  processes of ``mi-grg experiment``).

The estimates are deliberately coarse (the largest arrays and their copies, not every
temporary): they exist to turn a crash or a swap storm into a message naming the size.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

GIB = float(2 ** 30)
#: Entries one Dr.Jit array can hold (32-bit indices).
MAX_ENTRIES = 2 ** 31
#: Where --max-memory is kept for this process and its children (GiB).
ENV_MAX_MEMORY = "MI_GRG_MAX_MEMORY"
#: Bytes per Gaussian while training: parameters (11 floats), their gradients, Adam's two
#: moments, densification statistics, the kNN graph (k = 6 neighbours, index and weight)
#: and the projector's per-Gaussian records, float32 each.
GAUSSIAN_BYTES = 4 * (11 * 4 + 4 + 2 * 6 + 32)
#: Bytes per (Gaussian, view) record and per (record, row) lane of the projector's plan.
RECORD_BYTES, LANE_BYTES = 128, 32
#: Bytes per lane of one Monte Carlo pass (a volpath path's state) and per film pixel.
PATH_BYTES, PIXEL_BYTES = 256, 64


class MemoryLimitError(ValueError):
    """An allocation that would not fit; the message names the sizes and the option."""


@dataclass(frozen=True)
class Need:
    """One allocation: what it is (with its shape), its bytes, and the entries of its
    largest single array."""
    what: str
    nbytes: float
    entries: int


def _shape(shape) -> str:
    return " x ".join(str(int(n)) for n in shape)


def _prod(shape) -> int:
    return math.prod(int(n) for n in shape)


def volume(shape, copies: int = 4, what: str = "volume") -> Need:
    """A float32 volume [x, y, z] held ``copies`` times (result, accumulator, ...)."""
    n = _prod(shape)
    return Need(f"{what} {_shape(shape)} (x{copies})", 4.0 * n * copies, n)


def projections(n_views: int, det, copies: int = 2, what: str = "projections") -> Need:
    """A float32 projection stack [view, v, u] held ``copies`` times."""
    n = int(n_views) * _prod(det)
    return Need(f"{what} {int(n_views)} x {_shape(det)} (x{copies})", 4.0 * n * copies, n)


def gaussians(n: int) -> Need:
    """``n`` Gaussians with what training keeps per Gaussian (``GAUSSIAN_BYTES``)."""
    return Need(f"{int(n)} Gaussians", float(GAUSSIAN_BYTES) * int(n), int(n))


def plans(records: int, lanes: int, pixels: int, threads: int | None = None) -> Need:
    """The projector's work plan: at most ``records`` (Gaussian, view) records and
    ``lanes`` (record, row) lanes at once, and a chunk image of ``pixels`` floats copied
    per thread (Dr.Jit's Expand reduction)."""
    threads = threads or os.cpu_count() or 1
    nbytes = RECORD_BYTES * records + LANE_BYTES * lanes + 4.0 * pixels * threads
    return Need(f"projector plan ({int(records)} records, {int(lanes)} lanes)", nbytes,
                max(int(records), int(lanes), int(pixels)))


def film(n_views: int, det, spp: int, max_lanes: int) -> Need:
    """A Monte Carlo render of ``n_views`` films [v, u]: the pixels (images and their
    statistics) and one pass of at most ``max_lanes`` paths (at least one per pixel)."""
    pixels = int(n_views) * _prod(det)
    lanes = max(min(pixels * int(spp), int(max_lanes)), pixels)
    return Need(f"film {int(n_views)} x {_shape(det)} at {int(spp)} spp",
                PIXEL_BYTES * float(pixels) + PATH_BYTES * float(lanes), lanes)


def set_max_memory(gib) -> None:
    """Use ``gib`` GiB as the limit in this process and the processes it starts (None:
    the machine's available memory)."""
    if gib is None:
        os.environ.pop(ENV_MAX_MEMORY, None)
        return
    gib = float(gib)
    if not (math.isfinite(gib) and gib > 0):
        raise MemoryLimitError(f"--max-memory {gib:g}: expected GiB > 0")
    os.environ[ENV_MAX_MEMORY] = repr(gib)


def available_bytes() -> float:
    """The machine's available memory (Linux: MemAvailable), else half its memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2
    except (ValueError, OSError, AttributeError):
        return 8 * GIB


def limit() -> tuple:
    """(bytes, where the limit comes from)."""
    given = os.environ.get(ENV_MAX_MEMORY)
    if given:
        try:
            gib = float(given)
        except ValueError:
            gib = math.nan
        if not (math.isfinite(gib) and gib > 0):
            raise MemoryLimitError(f"{ENV_MAX_MEMORY}={given!r}: expected GiB > 0")
        return gib * GIB, f"the limit of {gib:.3g} GiB (--max-memory)"
    free = available_bytes()
    return free, (f"the {free / GIB:.3g} GiB this machine has available (--max-memory GIB "
                  "sets the limit)")


def check(needs, where: str, lower: str = "lower the sizes") -> float:
    """Refuse (``MemoryLimitError``, one line) when an array of ``needs`` cannot be built
    or their sum is above ``limit()``; ``where`` names what asks for them (a command, a
    file), ``lower`` what to change. Returns the estimate in bytes."""
    needs = list(needs)
    for n in needs:
        if n.entries >= MAX_ENTRIES:
            raise MemoryLimitError(f"{where}: {n.what} has {n.entries:.3g} entries in one "
                                   f"array, above the {MAX_ENTRIES:.3g} one array can hold; "
                                   f"{lower}")
    total = sum(n.nbytes for n in needs)
    cap, source = limit()
    if total > cap:
        parts = ", ".join(f"{n.what} {n.nbytes / GIB:.3g} GiB" for n in needs)
        raise MemoryLimitError(f"{where}: needs about {total / GIB:.3g} GiB ({parts}), above "
                               f"{source}; {lower}")
    return total
