"""Training checkpoints: what a run's state is, and its file (``checkpoint.npz``).

A checkpoint holds the ``TrainState`` (parameters, RNG, log, kept state, graph positions)
and the state of every stateful part through its ``state_dict()``: the optimiser
(``Adam``), the densifier (``PGADensifier``) and the early stopper (``EarlyStopper``).
Resuming from it continues the run where it stopped (the same views, the same
densification decisions up to float-atomic order). Files are written atomically: a crash
while writing leaves the previous checkpoint.

File layout (one ``.npz``; the same as before this module existed, so older files
load): ``raw__<key>`` / ``kept__<key>`` parameter arrays, ``kept_density_scale``,
``graph_positions`` [N, 3], ``adam_m__<group>`` / ``adam_v__<group>`` [N, C],
``dens_grad`` / ``dens_count`` [N] and ``meta`` (JSON: iteration, rng, log, stopper,
stopped_by, seconds, wall_seconds, config, adam_steps, time_plan, automatic).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.training.config import (AFTER_TRAINING, AUTO_FIELDS, BOOKKEEPING, TRAIN_EXTENT,
                                    TrainConfig, iterations_for_size)

#: The file name inside a run's output folder.
CHECKPOINT_NAME = "checkpoint.npz"

# Fields added after runs had been made, with the value that reproduces the behaviour
# from before they existed: a recorded config (a checkpoint's, a finished run's) that
# lacks one of them was made with this value (load_checkpoint, and
# mi_grg.lab.staleness.stale_keys). A field added with a default that CHANGES behaviour
# must not be listed, so that such runs count as stale and such checkpoints do not resume.
ADDED_LATER = {"rebuild_keeps_field": False, "holdout_until": 1.0, "time_budget": None,
               "holdout_catch_up": False, "stop_noise": 0.0, "init": "fdk",
               "frozen_step": False, "refine": "none", "refine_anchor": "on",
               "refine_fall": 1.0, "refine_tol": 0.0, "fit_rate_scale": 1.0,
               # before it, the schedule stretched to the run's count: the same as today's
               # None wherever the count was at most the rule's (staleness._auto_changed)
               "horizon": None,
               # R2-Gaussian's rules, constants of the densifier before they were settings
               "clone_scale_fraction": 0.1, "split_scale_factor": 1.6, "min_density": 1e-5,
               "bbox_margin": 0.0, "field_blur": "none", "data_loss": "l1"}


def upgrade_config_dict(values: dict) -> dict:
    """A recorded config (checkpoint, metrics.json) in today's spelling: fields of
    ``AUTO_FIELDS`` recorded as 0 (automatic, before they became optional) become None."""
    return {k: (None if k in AUTO_FIELDS and v == 0 and not isinstance(v, bool) else v)
            for k, v in values.items()}


@dataclass
class TrainState:
    """The training loop's own state (explicit, so that resuming is exact)."""
    iteration: int
    raw: dict
    rng: dict
    log: list = field(default_factory=list)
    kept_raw: dict | None = None
    kept_density_scale: object = None
    graph_positions: object = None   # positions [N, 3] the current graph was built from
    stopped_by: str | None = None
    seconds: float = 0.0             # training time (the loop's, cumulative over resumes)
    wall_seconds: float = 0.0        # wall clock from the run's start (De-Init included) to
                                     # this state, over every call that resumed it
    time_plan: dict | None = None    # the plan of a time_budget run (mi_grg.training.budget)


_RAW_TYPES = {"positions": "Point3f", "raw_scales": "Vector3f", "raw_rotations": "Vector4f",
              "raw_densities": "Float"}


def _raw_to_numpy(raw: dict) -> dict:
    out = {}
    for k, v in raw.items():
        if dr.size_v(v) == 0:  # scalar-like
            out[k] = np.asarray(v)
        elif hasattr(v, "__len__") and dr.depth_v(v) > 1 and dr.size_v(v) > 1:
            out[k] = np.stack([np.asarray(c) for c in v], -1)
        else:
            out[k] = np.asarray(v)
    return out


def _raw_from_numpy(arrs: dict) -> dict:
    out = {}
    for k, t in _RAW_TYPES.items():
        a = np.asarray(arrs[k], np.float32)
        cls = getattr(mi, t)
        # Dr.Jit maps a contiguous NumPy array instead of copying it; a resumed run that
        # read parameters mapped onto the file's arrays crashed (segfault): copies of its own
        out[k] = (cls(np.array(a)) if t == "Float"
                  else cls(*[mi.Float(a[:, i]) for i in range(a.shape[1])]))
    return out


def _atomic_savez(path: Path, **arrays) -> None:
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)  # never leaves a half-written checkpoint behind


def resolved_automatic(cfg: TrainConfig, n: int) -> dict:
    """What this code resolves ``cfg``'s automatic iteration count and extent to at grid
    size n = max(nVoxel) (only the fields left automatic; a time_budget plans its own
    count, which its checkpoint keeps in ``time_plan``)."""
    out = {}
    if cfg.schedule.iterations is None and cfg.run.time_budget is None:
        out["iterations"] = iterations_for_size(int(n))
    if cfg.schedule.extent is None:
        out["extent"] = TRAIN_EXTENT
    return out


def automatic_changes(meta: dict, cfg: TrainConfig) -> list:
    """The automatic fields that a checkpoint's run resolved otherwise than this code
    would resolve ``cfg``'s (a rule changed between the run's start and its resume), as
    "name (automatic: THEN then, NOW now)"; [] for checkpoints that record none (older
    code)."""
    then = meta.get("automatic")
    if not then:
        return []
    now = resolved_automatic(cfg, then["n"])
    return [f"{k} (automatic: {then[k]} then, {v} now)" for k, v in sorted(now.items())
            if k in then and then[k] != v]


def save_checkpoint(path, state: TrainState, optimizer, densifier, stopper,
                    cfg: TrainConfig, n: int) -> None:
    """Write ``state`` and the state_dict() of ``optimizer`` (Adam), ``densifier``
    (PGADensifier) and ``stopper`` (EarlyStopper) to ``path`` (atomically); ``n`` =
    max(nVoxel) records what the automatic fields resolved to (``automatic_changes``)."""
    arrays = {f"raw__{k}": v for k, v in _raw_to_numpy(state.raw).items()}
    if state.kept_raw is not None:
        arrays.update({f"kept__{k}": v for k, v in _raw_to_numpy(state.kept_raw).items()})
        if state.kept_density_scale is not None:
            arrays["kept_density_scale"] = np.asarray(state.kept_density_scale)
    if state.graph_positions is not None:
        arrays["graph_positions"] = np.asarray(state.graph_positions, np.float32)
    opt = optimizer.state_dict()   # {group: {"m": [N, C], "v": [N, C], "step": int}}
    for name, st in opt.items():
        arrays[f"adam_m__{name}"] = st["m"]
        arrays[f"adam_v__{name}"] = st["v"]
    dens = densifier.state_dict()  # {"grad_accum": [N] | None, "view_count": [N] | None}
    if dens["grad_accum"] is not None:
        arrays["dens_grad"] = dens["grad_accum"]
        arrays["dens_count"] = dens["view_count"]
    # Before the first evaluation the stopper has seen nothing: stored as None, as always.
    stop = stopper.state_dict() if stopper.history or stopper.seen else None
    meta = {"iteration": state.iteration, "rng": state.rng, "log": state.log,
            "stopper": stop, "stopped_by": state.stopped_by,
            "seconds": state.seconds, "wall_seconds": state.wall_seconds,
            "config": cfg.to_flat(), "time_plan": state.time_plan,
            "adam_steps": {g: st["step"] for g, st in opt.items()},
            "automatic": {"n": int(n), **resolved_automatic(cfg, n)}}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    _atomic_savez(Path(path), **arrays)


def load_checkpoint(path, optimizer, densifier, stopper, cfg: TrainConfig) -> TrainState:
    """Read a checkpoint written by ``save_checkpoint`` (of this or an earlier version):
    restores ``optimizer``, ``densifier`` and ``stopper`` through load_state_dict() and
    returns the ``TrainState``. A checkpoint of another config is an error that names the
    differing fields (resuming must continue the same run; ``BOOKKEEPING`` and
    ``AFTER_TRAINING`` fields may differ), and so is one whose automatic fields this code
    resolves otherwise (``automatic_changes``)."""
    with _open(path) as f:
        meta = _meta(f, path)
        changed = config_changes(meta["config"], cfg)
        if changed:
            raise ValueError(f"checkpoint {path} was made with a different config "
                             f"(differs in {changed}); resume with the same options")
        changed = automatic_changes(meta, cfg)
        if changed:
            raise ValueError(f"checkpoint {path} was made by code that resolved the automatic "
                             f"settings otherwise: {', '.join(changed)}; start the run afresh "
                             "(without its checkpoint), or resume it with the code that "
                             "started it")
        raw, kept = _raw_block(f, "raw"), _raw_block(f, "kept")
        opt_state = {}
        for name, step in meta["adam_steps"].items():
            opt_state[name] = {"m": f[f"adam_m__{name}"], "v": f[f"adam_v__{name}"],
                               "step": step}
        if opt_state:
            optimizer.load_state_dict(opt_state, like=raw)
        has_dens = "dens_grad" in f.files
        densifier.load_state_dict({"grad_accum": f["dens_grad"] if has_dens else None,
                                   "view_count": f["dens_count"] if has_dens else None})
        if meta["stopper"]:
            stopper.load_state_dict(meta["stopper"])
        kept_ds = (mi.Float(np.array(f["kept_density_scale"])) if "kept_density_scale" in f.files
                   else None)
        graph_pos = f["graph_positions"] if "graph_positions" in f.files else None
    return TrainState(iteration=meta["iteration"], raw=raw, rng=meta["rng"], log=meta["log"],
                      kept_raw=kept, kept_density_scale=kept_ds,
                      stopped_by=meta["stopped_by"], seconds=meta["seconds"],
                      # older files: the training time, the part of the wall clock they kept
                      wall_seconds=meta.get("wall_seconds", meta["seconds"]),
                      graph_positions=graph_pos, time_plan=meta.get("time_plan"))


def config_changes(recorded: dict, cfg: TrainConfig) -> list:
    """The training fields in which a checkpoint's ``recorded`` config (meta["config"])
    differs from ``cfg``: a resume must continue the same run, so any is an error
    (``BOOKKEEPING`` and ``AFTER_TRAINING`` fields may differ). Older checkpoints spell
    "automatic" as 0 for the fields that are None now, and lack fields added since (their
    value then: ADDED_LATER)."""
    used = upgrade_config_dict({**ADDED_LATER, **recorded})
    want = cfg.to_flat()
    return sorted(k for k in set(used) | set(want)
                  if used.get(k) != want.get(k) and k not in BOOKKEEPING + AFTER_TRAINING)


def checkpoint_config_changes(path, cfg: TrainConfig) -> list:
    """``config_changes`` and ``automatic_changes`` of the checkpoint at ``path`` against
    ``cfg`` ([]: it resumes)."""
    with _open(path) as f:
        meta = _meta(f, path)
        return config_changes(meta["config"], cfg) + automatic_changes(meta, cfg)


def raw_parameters(path, which: str = "raw") -> dict | None:
    """The raw parameters (``Gaussians.from_raw``'s input) of a checkpoint, checked as a
    resume checks them: ``which`` "raw" (the last state) or "kept" (the early stop's kept
    state; None where the checkpoint holds none)."""
    if which not in ("raw", "kept"):
        raise ValueError(f"which must be 'raw' or 'kept', got {which!r}")
    with _open(path) as f:
        return _raw_block(f, which)


def _raw_block(f, prefix: str) -> dict | None:
    """The parameter block ``prefix`` ("raw", "kept") of an open checkpoint; None if absent."""
    if f"{prefix}__positions" not in f.files:
        return None
    return _raw_from_numpy({k: f[f"{prefix}__{k}"] for k in _RAW_TYPES})


def checkpoint_time_plan(path) -> dict | None:
    """The time plan recorded in a checkpoint (None: none). A resumed time_budget run needs
    it before it can build its schedule."""
    with _open(path) as f:
        return _meta(f, path).get("time_plan")


def _open(path):
    from mi_grg.training.checkpoint_file import read_checkpoint
    return read_checkpoint(path, _RAW_TYPES)


def _meta(f, path) -> dict:
    from mi_grg.training.checkpoint_file import checked_meta
    return checked_meta(f, path, _RAW_TYPES)
