"""Whether a finished run is stale: what its record (metrics.json) says it was run with,
against what this code would run it with today.

The lab reuses a finished run only if it is not stale (``mi_grg.lab.reuse``), and the
report flags stale runs. Deciding that needs the history of the defaults: the iteration
rules that earlier runs recorded by name, what the automatic fields resolved to before
runs recorded it, and which options cannot change a run's result.
"""
from __future__ import annotations

import math

from mi_grg.protocol.split import holdout_split
from mi_grg.training.checkpoint import (ADDED_LATER, checkpoint_config_changes,
                                       upgrade_config_dict)
from mi_grg.training.config import (AFTER_TRAINING, BOOKKEEPING, FLAT_KEYS, ITERATION_RULE,
                                    PRESETS, TRAIN_EXTENT, TrainConfig, iterations_for_size,
                                    make_config)


def _rule_sqrt(n: int) -> int:
    return max(500, int(round(3000 * math.sqrt(n / 64))))


def _rule_1500(n: int) -> int:
    if n >= 64:
        return int(round(1500 * n / 64))
    return max(500, int(round(1500 * math.sqrt(n / 64))))


#: The automatic iteration rules by their recorded name: n = max(nVoxel) -> iterations.
#: ``stale_keys`` compares the count a run's recorded rule gave with today's, so that a
#: rule change marks only the sizes whose count it changed.
ITERATION_RULES = {
    "1500*n/64": _rule_1500,                    # the first rule (runs did not record it)
    "3000*sqrt(n/64)": _rule_sqrt,              # the second
    ITERATION_RULE: iterations_for_size,       # today's
}


#: Options of the held-out window (mi_grg.protocol.views): without held-out views
#: (holdout_every = 0) they change nothing, so a run made under other values is not stale.
WINDOW_KEYS = ("holdout_until", "holdout_catch_up")
#: Options of the TV refinement and the fit back (mi_grg.training.result): without the
#: refinement (refine = "none": r2, gr-paper) they change nothing.
REFINE_KEYS = ("refine_lam", "refine_max_iterations", "refine_anchor", "refine_fall",
               "refine_tol", "refine_output", "fit_iterations", "fit_rate_scale")


def stale_keys(m: dict) -> list:
    """Training options of a finished r2/gr run (its metrics.json, read into ``m``) whose
    recorded values differ from what this code resolves the run's options to (a default
    changed since it ran; a field in ``ADDED_LATER`` that the record lacks counts as its old
    value); [] if none differ or the run is not a training run. An iterative classical run
    (sart, asd-pocs, pdhg) made before held-out stopping was its default returns ["stop"]; a
    run whose held-out views are not today's ``holdout_split`` (the first split held out 0, 8, 16, ...)
    adds "held_out_views", and such a classical run decided under another ``stop_noise``
    adds "stop_noise" (its stop margin; gr / r2: ``_margin_inert``). A gr / r2 run that
    left ``extent`` or ``iterations`` automatic and resolved them otherwise than this code
    (``TRAIN_EXTENT``, ``ITERATION_RULE``; the earliest runs record neither) adds
    "extent" / "iterations"."""
    if (m.get("method") in ("sart", "asd-pocs", "pdhg")
            and (m.get("options") or {}).get("stop", "heldout") == "heldout"
            and (m.get("method_info") or {}).get("protocol") != "heldout"):
        return ["stop"]     # ran a fixed sweep count before held-out stopping was the default
    split = ["held_out_views"] if _split_changed(m) else []
    if m.get("method") in ("sart", "asd-pocs", "pdhg"):
        rule = (m.get("method_info") or {}).get("stop_rule") or {}
        now = TrainConfig().protocol.stop_noise
        if rule and float(rule.get("noise", ADDED_LATER["stop_noise"])) != now:
            split.append("stop_noise")   # decided under another stop margin
    used = (m.get("method_info") or {}).get("config")
    if m.get("method") not in PRESETS or not isinstance(used, dict):
        return split
    opts = upgrade_config_dict({k: v for k, v in (m.get("options") or {}).items()
                                if k in FLAT_KEYS})
    try:
        now = make_config(m["method"], (m.get("options") or {}).get("config"), **opts).to_flat()
    except Exception:  # noqa: BLE001 (an option this code no longer accepts)
        return ["config"]
    recorded = set(used)
    used = upgrade_config_dict({**ADDED_LATER, **used})   # recorded values win
    differ = {k for k in set(now) | set(used)
              if now.get(k) != used.get(k) and k not in BOOKKEEPING}
    if now.get("holdout_every") == 0 and used.get("holdout_every") == 0:
        differ -= set(WINDOW_KEYS)     # no view held out: the window has nothing to act on
    if now.get("refine") == "none" and used.get("refine") == "none":
        differ -= set(REFINE_KEYS)     # no refinement: its options have nothing to act on
    if "stop_noise" in differ and _margin_inert(m, used, now):
        differ.discard("stop_noise")
    if _anchor_rule_changed(m, used):
        differ.add("refine_anchor")
    return sorted(differ | _auto_changed(m, used, recorded)) + split


def resumes(method: str, options: dict, checkpoint, stale: list | None) -> bool:
    """Whether a run to do (``method``, ``options``) continues from ``checkpoint`` instead
    of starting afresh. An interrupted run (``stale`` None: no metrics.json) does if the
    checkpoint was made under the training config this code gives the run; so does a
    finished run whose ``stale_keys`` all act after training (``AFTER_TRAINING``): its
    trained state is today's, and it redoes only the result's steps."""
    if stale is not None and not set(stale) <= set(AFTER_TRAINING):
        return False
    opts = upgrade_config_dict({k: v for k, v in options.items() if k in FLAT_KEYS})
    try:
        cfg = make_config(method, options.get("config"), **opts)
        return not checkpoint_config_changes(checkpoint, cfg)
    except Exception:  # noqa: BLE001 (unreadable, or options this code no longer takes)
        return False


def same_training(method: str, options_a: dict, options_b: dict) -> bool:
    """Whether two runs of ``method`` train the same state: their resolved configs agree on
    every field but those that act after training or only keep the books
    (``AFTER_TRAINING``, ``BOOKKEEPING``), and their other options are equal. Such runs
    share one training (``mi_grg.lab.reuse``: gr-paper resumes from gr's final checkpoint)."""
    if method not in PRESETS:
        return False
    skip = set(AFTER_TRAINING) | set(BOOKKEEPING)

    def resolved(options):
        opts = upgrade_config_dict({k: v for k, v in options.items() if k in FLAT_KEYS})
        flat = make_config(method, options.get("config"), **opts).to_flat()
        rest = {k: v for k, v in options.items() if k not in FLAT_KEYS and k != "config"}
        return {k: v for k, v in flat.items() if k not in skip}, rest
    try:
        return resolved(options_a) == resolved(options_b)
    except Exception:  # noqa: BLE001 (options this code does not take: no sharing)
        return False


#: What the automatic extent and iteration count resolved to in the earliest runs (which
#: do not record it): the projector's 4.5 and 1500 x n / 64 (sqrt below 64).
_OLD_AUTO = {"extent": 4.5, "iteration_rule": "1500*n/64"}


def _auto_changed(m: dict, used: dict, recorded: set) -> set:
    """Automatic fields (None in the run's config) that this code resolves differently
    from what the run recorded in method_info (``extent``, ``iteration_rule``), and
    ``horizon`` for a run from before it (``recorded``: its config's keys) that ran longer
    than the rule's count, whose schedule stretched to its own length."""
    info = m.get("method_info") or {}
    out = set()
    planned, nvox = info.get("iterations_planned"), m.get("nVoxel")
    if ("horizon" not in recorded and planned and nvox
            and int(planned) > iterations_for_size(max(nvox))):
        out.add("horizon")
    if (used.get("extent") is None
            and float(info.get("extent", _OLD_AUTO["extent"])) != TRAIN_EXTENT):
        out.add("extent")
    if used.get("iterations") is None and used.get("time_budget") is None:
        name = info.get("iteration_rule", _OLD_AUTO["iteration_rule"])
        rule, nvox = ITERATION_RULES.get(name), m.get("nVoxel")
        if nvox and rule is not None:     # the count at the run's size decides
            changed = rule(max(nvox)) != iterations_for_size(max(nvox))
        else:                             # no size recorded: the rule itself
            changed = name != ITERATION_RULE
        if changed:
            out.add("iterations")
    return out


def _anchor_rule_changed(m: dict, used: dict) -> bool:
    """Whether ``refine_anchor="auto"`` took the anchor, before densification's demand
    decided it (the record has no verdict), in a run whose count ended at its cap: today it
    refines such a run plain (``mi_grg.training.densify.demand``; a count still growing at
    the end of its window, the rule's other half, is not in such a record)."""
    from mi_grg.training.densify import DEMAND_CAP
    info = m.get("method_info") or {}
    anchor = (info.get("refine") or {}).get("anchor") or {}
    if (used.get("refine") != "tv" or used.get("refine_anchor") != "auto"
            or "densification" in anchor or not anchor.get("anchored")):
        return False
    n, cap = info.get("n_gaussians"), info.get("max_gaussians")
    return bool(n and cap and n >= DEMAND_CAP * cap)


def _margin_inert(m: dict, used: dict, now: dict) -> bool:
    """Whether today's larger ``stop_noise`` leaves a finished run as it was: the rule never
    fired and the run returned its last state, so a wider margin (which can only postpone a
    stop and only moves the kept state) changes nothing."""
    views = (m.get("method_info") or {}).get("views") or {}
    last = (m.get("method_info") or {}).get("iterations_run")
    return (float(now.get("stop_noise", 0)) >= float(used.get("stop_noise", 0))
            and "stop" in views and views["stop"] is None
            and last is not None and views.get("returned_state_iteration") == last)


def _split_changed(m: dict) -> bool:
    """Whether a finished run recorded held-out views other than the ones
    ``mi_grg.protocol.split.holdout_split`` gives its view count and ``holdout_every`` today."""
    info = m.get("method_info") or {}
    held, n = info.get("held_out_views"), m.get("n_train_views")
    # gr / r2 record their config; the classical methods their stop rule
    every = (info.get("config") or info.get("stop_rule") or {}).get("holdout_every")
    if held is None or n is None or every is None:
        return False
    return [int(v) for v in held] != holdout_split(int(n), int(every))[1].tolist()

