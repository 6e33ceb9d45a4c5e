"""Training hyperparameters: one dataclass, method presets, and XML config files.

Config files use Mitsuba's XML property syntax, so they read like the scene files::

    <training method="gr">
        <integer name="k" value="6"/>
        <float name="lambda_lap" value="8e-4"/>
        <boolean name="use_pga" value="true"/>
    </training>

Every key must be a field of ``TrainConfig`` (unknown or misspelled keys are an error, with
a suggestion) and the tag must match the field's type. Fields that can be chosen
automatically (``AUTO_FIELDS``) take ``value="none"`` (or are left out) for that, as does
``time_budget`` for "no budget". Command-line ``--option key=value`` pairs override the file, which overrides the method preset, which overrides the defaults.
Defaults are the GR-Gaussian paper's (Sec. 4.1.2) in R2-Gaussian's normalised units
(volume in [-1, 1]^3).
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields

from mi_grg.protocol.early_stop import KEEP_STATES, STOP_RULE

#: Fields whose None means "automatic" (each field's comment says what is chosen). Records
#: written before they were optional spell that 0 (``upgrade_config_dict``).
AUTO_FIELDS = ("iterations", "extent", "graph_s", "tv_extent", "log_3d_every",
               "checkpoint_every")

#: Fields that cannot change a run's result (when its checkpoints are written): a resume
#: may change them, and a finished run is not stale for them (``stale_keys``).
BOOKKEEPING = ("checkpoint_every", "frozen_step")

# Method presets: R2-Gaussian is GR-Gaussian with every graph component switched off.
PRESETS = {
    "gr": {},
    "r2": {"sigma_d": 0.0, "use_pga": False, "use_graph_field": False, "lambda_lap": 0.0},
}


# Fields added after runs had been made, with the value that reproduces the behaviour
# from before they existed: a finished run whose recorded config lacks one of them was
# made with this value (stale_keys). A field added with a default
# that CHANGES behaviour must not be listed, so that such runs count as stale.
ADDED_LATER = {"rebuild_keeps_field": False, "holdout_until": 1.0, "time_budget": None,
               "holdout_catch_up": False, "stop_noise": 0.0, "init": "fdk",
               "frozen_step": False}

#: The volumes De-Init can start from (``TrainConfig.init``).
INIT_VOLUMES = ("fdk", "pdhg")

#: Training's truncation extent (std devs) when ``TrainConfig.extent`` is None: the
#: projector, the logged 3-D PSNR and the output volume use it. Shorter than the
#: projector's 4.5: its truncation error is a small fraction of the noise of sparse noisy
#: views, and it saves training time (docs/benchmarks.md, "Training step").
TRAIN_EXTENT = 3.5

#: Iterations at 64^3 (``trainer.iteration_rule``): about what the 5-minute target buys on
#: this project's 2-core CPU at extent 3.5 (docs/benchmarks.md, "The iteration rule
#: re-derived").
ITERATIONS_AT_64 = 3000


def _rule_sqrt(n: int) -> int:
    return max(500, int(round(ITERATIONS_AT_64 * math.sqrt(n / 64))))


def _rule_linear_to_2x(n: int) -> int:
    if n <= 64:
        return _rule_sqrt(n)
    return int(round(ITERATIONS_AT_64 * min(n / 64, 2.0)))


def _rule_1500(n: int) -> int:
    if n >= 64:
        return int(round(1500 * n / 64))
    return max(500, int(round(1500 * math.sqrt(n / 64))))


#: Today's rule, as metrics.json records it (``method_info.iteration_rule``).
ITERATION_RULE = "3000*sqrt(n/64) to 64, 3000*min(n/64,2) above"
#: The automatic iteration rules by their recorded name: n = max(nVoxel) -> iterations.
#: ``stale_keys`` compares the count a run's recorded rule gave with today's, so that a
#: rule change marks only the sizes whose count it changed.
ITERATION_RULES = {
    "1500*n/64": _rule_1500,                    # the first rule (runs did not record it)
    "3000*sqrt(n/64)": _rule_sqrt,              # the second
    ITERATION_RULE: _rule_linear_to_2x,
}


#: Options of the held-out window (mi_grg.protocol.views): without held-out views
#: (holdout_every = 0) they change nothing, so a run made under other values is not stale.
WINDOW_KEYS = ("holdout_until", "holdout_catch_up")


@dataclass
class TrainConfig:
    """Every hyperparameter of GR-Gaussian / R2-Gaussian training."""

    # --- schedule
    iterations: int | None = None  # None: scaled to the problem size
                                   # (mi_grg.training.trainer.iteration_rule)
    seed: int = 0                  # same seed, same run up to float atomics: the scatter-
                                   # adds sum in thread order, so volumes of two runs differ
                                   # slightly (docs/benchmarks.md)
    extent: float | None = None    # Gaussian support in std devs; None: TRAIN_EXTENT
                                   # (shorter than the projector's default 4.5)
    # --- De-Init (Sec. 3.3.1)
    init: str = "fdk"              # the volume De-Init samples: "fdk" (the paper's FDK of
                                   # the fitted views) or "pdhg" (PDHG's TV reconstruction
                                   # of the fitted views, its weight and iterations chosen
                                   # on their own held-out views: mi_grg.protocol.heldout)
    n_points: int = 50000          # M, capped by the number of candidate voxels
    init_tau: float = 0.001        # threshold, fraction of the denoised volume's max
    sigma_d: float = 3.0           # denoising filter std in voxels of a sigma_d_grid grid;
                                   # 0: plain FDK init (R2)
    sigma_d_grid: int = 256        # sigma_d is a length: sigma_d / sigma_d_grid of the volume's
                                   # longest edge (the paper's 3 voxels at 256^3), filtered
                                   # as sigma_d x max(nVoxel) / sigma_d_grid voxels of the
                                   # case (0.75 at 64^3); 0: sigma_d in the case's voxels
    density_rescale: float = 0.15  # init densities x this (kernel overlap; R2-Gaussian's)
    # --- graph (Sec. 3.2)
    use_graph_field: bool = True   # Eq. 10/13 graph-augmented density field
    k: int = 6                     # neighbours in the kNN graph
    graph_s: float | None = None   # weight scale s in exp(-d^2 / s); None: automatic
                                   # (mi_grg.training.graph.default_scale)
    rebuild_keeps_field: bool = False  # after densification, rescale the densities so that
                                   # the rebuilt graph alone does not change the field:
                                   # each kernel keeps its source's multiplier 1 + sum w
                                   # (why: mi_grg.training.trainer.carry_density_scale)
    lambda_lap: float = 8e-4       # graph Laplacian weight (raw sum x 50k / N, see train)
    # --- PGA densification (Sec. 3.3.2); the schedule (densify_start/stop/interval and
    # eval_every) is the paper's for 30k iterations and is scaled to the run's length
    use_pga: bool = True           # graph term in the densification gradient
    lambda_g: float = 1e-4         # paper's; at 64^3 its term is small against the
                                   # gradient term, so PGA barely changes densification
                                   # (docs/benchmarks.md)
    densify_interval: int = 100
    densify_start: int = 500
    densify_stop: int = 15000
    densify_grad_threshold: float = 5e-5   # tau_pos (R2-Gaussian's default)
    max_gaussians: int = 500000    # cap on the count (R2-Gaussian's) ...
    max_gaussians_per_voxel: float = 0.5  # ... and at most this x prod(nVoxel); 0: no such
                                   # cap. Why: past about half the voxel count the extra
                                   # Gaussians cannot add detail the grid resolves, only
                                   # time (docs/benchmarks.md)
    # --- losses
    lambda_ssim: float = 0.25
    lambda_tv: float = 0.05
    tv_block: int = 32             # edge of the randomly placed TV block, voxels
    tv_extent: float | None = 3.0  # Gaussian support in std devs inside the TV block;
                                   # None: ``extent``. 3 is the 3-sigma cut of 3DGS-style
                                   # rasterisers; it needs (3/4.5)^3 = 0.3x the voxel pairs
    tv_every: int = 2              # TV on every n-th iteration only, weighted n x lambda_tv:
                                   # the same expected gradient (the block is random anyway)
                                   # for half the TV cost (docs/benchmarks.md)
    # --- Adam learning rates (decay exponentially to lr_final_ratio of these)
    lr_position: float = 2e-4
    lr_density: float = 1e-2
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    lr_final_ratio: float = 0.1
    # --- early stopping without ground truth
    holdout_every: int = STOP_RULE.holdout_every  # hold out every n-th training view; 0: none
    holdout_until: float = 0.667   # ... for this fraction of the iterations (the stop rule
                                   # decides only then), then train on every view; 1: held
                                   # out all run (mi_grg.protocol.views).
                                   # Why 2/3: the shortest window in which the rule can
                                   # still fire after densification (ends at 1/2)
    holdout_catch_up: bool = False # after that, draw the held-out views more often until
                                   # every view's expected draws are equal (candidate)
    eval_every: int = 500
    stop_drop: float = STOP_RULE.drop  # stop when held-out PSNR drops by more than this fraction
    stop_patience: int = STOP_RULE.patience  # ... below its best at this many evaluations in a row
                                   # (1: the paper's rule; why 2: mi_grg.protocol.early_stop)
    stop_noise: float = STOP_RULE.noise  # ... and by more than this many times the held-out
                                   # PSNR's own scatter between evaluations (0: stop_drop
                                   # alone; why: mi_grg.protocol.early_stop)
    keep_state: str = STOP_RULE.keep  # state kept: "latest" within the stop margin of the best
                                   # held-out PSNR, or "best" (why: mi_grg.protocol.early_stop)
    refit_iterations: int = 0      # brief refit on all views after stopping
    monitor_3d: bool = False       # RESEARCH ONLY: stop on 3-D PSNR vs ground truth instead
    log_3d_every: int | None = None  # log 3-D PSNR vs ground truth every n iterations
                                   # (no effect on training); None: at each held-out
                                   # evaluation
    # --- bookkeeping
    checkpoint_every: int | None = None  # iterations between checkpoints; None: a tenth
                                   # of the run, 1 to 500 (trainer.checkpoint_interval), so
                                   # that a short run has them too
    time_budget: float | None = None  # seconds for the whole training (De-Init to the
                                   # returned state): the iteration count and schedule are
                                   # planned from a probe of this machine's speed instead of
                                   # iteration_rule (mi_grg.training.budget); None: no budget
    frozen_step: bool = False      # record the iterations without TV block once with
                                   # dr.freeze and replay them (no Python tracing per
                                   # iteration; mi_grg.training.frozen_step): the same
                                   # results, less host time

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(f"{f.name} must be finite, got {v}")
        if self.time_budget is not None:
            if not self.time_budget > 0:
                raise ConfigError(f"time_budget must be > 0 seconds (or none: no budget), "
                                  f"got {self.time_budget!r}")
            if self.iterations is not None:
                raise ConfigError(f"time_budget ({self.time_budget:g} s) plans the iteration "
                                  f"count; iterations={self.iterations} would override it: "
                                  "give one of them")
        for name in AUTO_FIELDS:
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ConfigError(f"{name} must be > 0 or none (automatic), got {v!r}; "
                                  "0 no longer means automatic: write none or leave it out")
        nonneg = [f.name for f in fields(self) if _base_type(f) in ("int", "float")
                  and getattr(self, f.name) is not None and getattr(self, f.name) < 0]
        if nonneg:
            raise ConfigError(f"must be >= 0: {', '.join(nonneg)}")
        if self.k < 1:
            raise ConfigError("k must be >= 1")
        if not 0 < self.lr_final_ratio <= 1:
            raise ConfigError("lr_final_ratio must be in (0, 1]")
        if self.n_points < 1:
            raise ConfigError("n_points must be >= 1")
        if not 0.0 <= self.holdout_until <= 1.0:
            raise ConfigError(f"holdout_until must be a fraction in [0, 1], got "
                              f"{self.holdout_until}")
        if self.init not in INIT_VOLUMES:
            raise ConfigError(f"init must be one of {', '.join(INIT_VOLUMES)}, got "
                              f"{self.init!r}")
        if self.keep_state not in KEEP_STATES:
            raise ConfigError(f"keep_state must be one of {', '.join(KEEP_STATES)}, "
                              f"got {self.keep_state!r}")
        zero = [n for n in ("eval_every", "densify_interval", "tv_every",
                            "stop_patience") if getattr(self, n) < 1]
        if zero:
            raise ConfigError(f"must be >= 1 (iterations or evaluations): {', '.join(zero)}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class ConfigError(ValueError):
    """An invalid or unknown configuration key; the message names it."""


def _base_type(f) -> str:
    """A field's type without "| None" ("int", "float", "bool" or "str")."""
    return f.type.replace(" | None", "")


def upgrade_config_dict(values: dict) -> dict:
    """A recorded config (checkpoint, metrics.json) in today's spelling: fields of
    ``AUTO_FIELDS`` recorded as 0 (automatic, before they became optional) become None."""
    return {k: (None if k in AUTO_FIELDS and v == 0 and not isinstance(v, bool) else v)
            for k, v in values.items()}


_FIELDS = {f.name: f for f in fields(TrainConfig)}
_TAG_OF_TYPE = {"int": "integer", "float": "float", "bool": "boolean", "str": "string"}
_NONE_WORDS = ("none", "null")


def _check_key(key: str) -> None:
    if key not in _FIELDS:
        close = difflib.get_close_matches(key, list(_FIELDS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"unknown training option {key!r}{hint}")


def _coerce(key: str, value):
    _check_key(key)
    kind = _base_type(_FIELDS[key])
    if "| None" in _FIELDS[key].type and (value is None or (
            isinstance(value, str) and value.strip().lower() in _NONE_WORDS)):
        return None
    try:
        if kind == "bool":
            if isinstance(value, str):
                if value.lower() not in ("true", "false"):
                    raise ValueError
                return value.lower() == "true"
            if not isinstance(value, bool):
                raise ValueError
            return value
        if kind == "str":
            if not isinstance(value, str):
                raise ValueError
            return value
        if kind == "int":
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} expects a {kind}, got {value!r}") from None


def read_config_xml(path) -> tuple[str | None, dict]:
    """Parse a training config file; returns (method or None, {key: value})."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise ConfigError(f"cannot read config {path}: {e}") from None
    if root.tag != "training":
        raise ConfigError(f"{path}: root element must be <training>, got <{root.tag}>")
    unknown_attr = set(root.attrib) - {"method", "version"}
    if unknown_attr:
        raise ConfigError(f"{path}: unknown attribute(s) {sorted(unknown_attr)} on <training>")
    method = root.attrib.get("method")
    values = {}
    for el in root:
        if el.tag is ET.Comment or not isinstance(el.tag, str):
            continue
        name, value = el.attrib.get("name"), el.attrib.get("value")
        if name is None or value is None:
            raise ConfigError(f"{path}: <{el.tag}> needs name and value attributes")
        _check_key(name)
        want = _TAG_OF_TYPE[_base_type(_FIELDS[name])]
        if el.tag != want:
            raise ConfigError(f"{path}: {name} is a {_base_type(_FIELDS[name])}; write <{want} "
                              f"name=\"{name}\" .../>, not <{el.tag}>")
        if name in values:
            raise ConfigError(f"{path}: {name} is given twice")
        values[name] = _coerce(name, value)
    return method, values


def write_config_xml(config: TrainConfig, path, method: str | None = None) -> None:
    """Write every field of ``config`` (a complete, self-documenting config file); a field
    left automatic is written as value="none"."""
    method_attr = f' method="{method}"' if method else ""
    lines = [f'<training version="1"{method_attr}>']
    for f in fields(config):
        v = getattr(config, f.name)
        text = ("none" if v is None else str(v).lower() if isinstance(v, bool)
                else v if isinstance(v, str) else repr(v))
        lines.append(f'    <{_TAG_OF_TYPE[_base_type(f)]} name="{f.name}" value="{text}"/>')
    lines.append("</training>\n")
    with open(path, "w") as fh:
        fh.write("\n".join(lines))


def make_config(method: str = "gr", path=None, **overrides) -> TrainConfig:
    """Defaults <- method preset <- config file <- overrides (each key validated)."""
    if method not in PRESETS:
        raise ConfigError(f"unknown method {method!r}; presets: {sorted(PRESETS)}")
    values = dict(PRESETS[method])
    if path is not None:
        file_method, file_values = read_config_xml(path)
        if file_method is not None and file_method != method:
            raise ConfigError(f"{path} is a config for method {file_method!r}, not {method!r}")
        values.update(file_values)
    for key, value in overrides.items():
        values[key] = _coerce(key, value)
    return TrainConfig(**values)


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
        if rule and float(rule.get("noise", ADDED_LATER["stop_noise"])) != TrainConfig().stop_noise:
            split.append("stop_noise")   # decided under another stop margin
    used = (m.get("method_info") or {}).get("config")
    if m.get("method") not in PRESETS or not isinstance(used, dict):
        return split
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    opts = upgrade_config_dict({k: v for k, v in (m.get("options") or {}).items()
                                if k in names})
    try:
        now = make_config(m["method"], (m.get("options") or {}).get("config"), **opts).to_dict()
    except Exception:  # noqa: BLE001 (an option this code no longer accepts)
        return ["config"]
    used = upgrade_config_dict({**ADDED_LATER, **used})   # recorded values win
    differ = {k for k in set(now) | set(used)
              if now.get(k) != used.get(k) and k not in BOOKKEEPING}
    if now.get("holdout_every") == 0 and used.get("holdout_every") == 0:
        differ -= set(WINDOW_KEYS)     # no view held out: the window has nothing to act on
    if "stop_noise" in differ and _margin_inert(m, used, now):
        differ.discard("stop_noise")
    return sorted(differ | _auto_changed(m, used)) + split


#: What the automatic extent and iteration count resolved to in the earliest runs (which
#: do not record it): the projector's 4.5 and 1500 x n / 64 (sqrt below 64).
_OLD_AUTO = {"extent": 4.5, "iteration_rule": "1500*n/64"}


def _auto_changed(m: dict, used: dict) -> set:
    """Automatic fields (None in the run's config) that this code resolves differently
    from what the run recorded in method_info (``extent``, ``iteration_rule``)."""
    info = m.get("method_info") or {}
    out = set()
    if (used.get("extent") is None
            and float(info.get("extent", _OLD_AUTO["extent"])) != TRAIN_EXTENT):
        out.add("extent")
    if used.get("iterations") is None and used.get("time_budget") is None:
        name = info.get("iteration_rule", _OLD_AUTO["iteration_rule"])
        rule, nvox = ITERATION_RULES.get(name), m.get("nVoxel")
        if nvox and rule is not None:     # the count at the run's size decides
            changed = rule(max(nvox)) != ITERATION_RULES[ITERATION_RULE](max(nvox))
        else:                             # no size recorded: the rule itself
            changed = name != ITERATION_RULE
        if changed:
            out.add("iterations")
    return out


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
    from mi_grg.protocol.split import holdout_split
    info = m.get("method_info") or {}
    held, n = info.get("held_out_views"), m.get("n_train_views")
    # gr / r2 record their config; the classical methods their stop rule
    every = (info.get("config") or info.get("stop_rule") or {}).get("holdout_every")
    if held is None or n is None or every is None:
        return False
    return [int(v) for v in held] != holdout_split(int(n), int(every))[1].tolist()

