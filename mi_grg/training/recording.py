"""The training iteration recorded once with Dr.Jit's frozen functions (``dr.freeze``) and
replayed: no Python tracing, no host read inside it.

What is recorded: ``mi_grg.training.step.recorded_step``, i.e. ``loss_and_grads`` (one
recording with the TV block, one without) and, when its inputs are given, the
densification statistics and Adam (their results are outputs, applied by the caller once
the replay is checked: ``PGADensifier.add``, ``Adam.apply``). What stays outside (the
trainer): the draws (view, block corner), the loss read (the one host synchronisation of
an iteration, as on the traced path), evaluation, logging, densification and graph
rebuilds.

The traced step reads data-dependent sizes on the host (the projector's footprint rows and
near-source records, the voxelizer's pair plan); a recording cannot. Here they are
capacities fixed when the step is recorded: ``rows`` (record, row) lanes and ``near``
near-source record slots (none until one is seen) for the projection (``RowCapacity``),
``cols`` column and ``slices`` slice lanes for the TV block
(``voxelizer.capacity_plan``). The lanes past the counts are the tail of each launch and
run inside a symbolic conditional, so whole SIMD packets of them skip their work (a
masked lane costs about a real one's set-up otherwise). The counts come back with the
result; a count past its capacity discards the result, the iteration runs traced, the
capacity grows and the next call records anew. Each kind of event is said once
(``Recording.note``). Recordings are keyed by the Gaussian count, the graph's sizes and
the capacities: densification and graph rebuilds record anew.

Exact: the recorded step evaluates the same expressions as the traced one; only the lane
counts differ (lanes past the counts add nothing). docs/frozen_step.md lists the traced
step's host reads and where each went.
"""
from __future__ import annotations

import dataclasses
import gc
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.training.step import StepConfig, StepInputs, owned, recorded_step

# Headroom of a capacity over the most lanes per Gaussian seen so far (the rows vary with
# the view, the pairs with the block), and its granularity (so that small changes keep a
# recording)
HEADROOM = 1.25
QUANTUM = {"rows": 4096, "cols": 4096, "slices": 4096, "near": 16}
# Lanes (near: records) per Gaussian before any count was seen (an overflow then sets
# the real one); near-source records are rare: none until one is seen
INITIAL_PER_GAUSSIAN = {"rows": 4.0, "cols": 2.0, "slices": 1.0, "near": 0.0}


class _Holder:
    """The step's constants (not a PyTree: the frozen function keys it by identity)."""

    def __init__(self, cfg: StepConfig):
        self.cfg = cfg


class Recording:
    """The recorded iteration for one ``StepConfig`` (see the module docstring).

    ``step(inputs, update)`` returns the replay's outputs (a dict: loss, grads, gnorm,
    counts; with ``update`` also stats, raw, m, v) and the loss value, or None when this
    iteration must run traced (nothing of the replay is kept)."""

    def __init__(self, cfg: StepConfig, log=print):
        self.holder = _Holder(cfg)
        self.targets = {}
        # one recording per kind of iteration (with and without TV block), replaced when
        # its key changes; re-recording after a densification is expected, not a warning
        self.fn = {False: dr.freeze(recorded_step, limit=1, warn_after=1 << 30),
                   True: dr.freeze(recorded_step, limit=1, warn_after=1 << 30)}
        self.per_gaussian = dict(INITIAL_PER_GAUSSIAN)
        self.capacity = {}          # kind -> (N, lanes) of the current recordings
        self.log, self.said = log, set()
        self.replays = self.fallbacks = 0

    @property
    def n_recordings(self) -> int:
        return sum(f.n_recordings for f in self.fn.values())

    def note(self, kind: str, text: str) -> None:
        """Say ``text`` once per kind of event (overflows are expected after growth)."""
        if kind not in self.said:
            self.said.add(kind)
            self.log(f"frozen step: {text}")

    def _target(self, target):
        """The target image in Dr.Jit's own memory (see ``step.owned``), kept per image."""
        kept = self.targets.get(id(target))
        if kept is None or kept[0] is not target:
            kept = self.targets[id(target)] = (target, mi.TensorXf(owned(target.array),
                                                                   target.shape))
        return kept[1]

    def lanes(self, kind: str, n: int) -> int:
        """Lanes of ``kind`` for N Gaussians: the most per Gaussian seen, with headroom."""
        cap = self.capacity.get(kind)
        if cap is None or cap[0] != n:
            quantum = QUANTUM[kind]
            q = math.ceil(self.per_gaussian[kind] * HEADROOM * max(n, 1) / quantum)
            cap = self.capacity[kind] = (n, q * quantum)
        return cap[1]

    def recordable(self, inputs: StepInputs) -> bool:
        """Whether this iteration can be recorded (else said once, and it runs traced)."""
        from mi_grg.core.projector import RECORDS_PER_CHUNK
        n = dr.width(inputs.raw["raw_densities"])
        if n == 0 or n > RECORDS_PER_CHUNK or (inputs.tv_start is not None
                                               and self.holder.cfg.tv is None):
            self.note("chunks", f"{n} Gaussians (or a TV block without its settings): "
                      "not recordable, traced")
            return False
        return True

    def run(self, inputs: StepInputs, update=None, adam_key=None):
        """The recorded computation on ``inputs`` (traced-step inputs: ``capacity`` and
        the TV corner's type are set here) and the key it ran under (lazy outputs of the
        replay). ``update``: the statistics' and Adam's inputs, ``adam_key`` Adam's
        (betas, eps)."""
        n = dr.width(inputs.raw["raw_densities"])
        graph = inputs.graph if inputs.lap_weight is not None else None
        if graph is not None:
            from mi_grg.training.graph import neighbour_table
            neighbour_table(graph)       # its host read, once per graph, outside
        tv = inputs.tv_start is not None
        rows = (self.lanes("rows", n), self.lanes("near", n))
        pairs = (self.lanes("cols", n), self.lanes("slices", n)) if tv else None
        key = (n, rows, None if graph is None else (graph.n, graph.num_edges, graph.table[0]),
               pairs, adam_key if update is not None else None)
        inputs = dataclasses.replace(
            inputs, raw={k: dr.detach(v) for k, v in inputs.raw.items()},
            target=self._target(inputs.target), graph=graph, capacity=(rows, pairs),
            tv_start=[dr.opaque(mi.Int32, int(s)) for s in inputs.tv_start] if tv else None)
        # Python's cycle collector must not run inside a recording or replay: collecting
        # another (dead) trainer's recorded function there aborts Dr.Jit.
        paused = gc.isenabled()
        gc.disable()
        try:
            return self.fn[tv](self.holder, inputs, update, key), key
        finally:
            if paused:
                gc.enable()

    def check(self, out: dict, key: tuple) -> float | None:
        """The loss value, or None: the result is incomplete (said once per kind); the
        capacity that overflowed grows for the next call."""
        vals = [np.asarray(out["loss"], np.float64).reshape(-1)[0]]
        vals += [int(np.asarray(c).reshape(-1)[0]) for c in out["counts"]]
        loss, rows, near, cols, slices = vals
        n = key[0]
        caps = {"rows": (rows, key[1][0]), "near": (near, key[1][1])}
        if key[3] is not None:
            caps.update(cols=(cols, key[3][0]), slices=(slices, key[3][1]))
        over = []
        for kind, (count, lanes) in caps.items():
            self.per_gaussian[kind] = max(self.per_gaussian[kind], count / max(n, 1))
            if count > lanes:
                over.append(f"{count} {kind} > {lanes}")
                self.capacity.pop(kind, None)      # the next call records with room
        if over:
            self.note("overflow", "lanes past the recorded capacity (" + ", ".join(over)
                      + "): the iteration runs traced and the next records a larger "
                      "capacity (said once)")
            return None
        return float(loss)

    def step(self, inputs: StepInputs, update=None, adam_key=None):
        """(outputs, loss value) of the replay, or None (run this iteration traced)."""
        if not self.recordable(inputs):
            self.fallbacks += 1
            return None
        out, key = self.run(inputs, update, adam_key)
        loss_value = self.check(out, key)
        if loss_value is None:
            self.fallbacks += 1
            return None
        self.replays += 1
        return out, loss_value
