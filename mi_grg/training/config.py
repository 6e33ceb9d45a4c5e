"""Training hyperparameters: one dataclass in named parts, method presets, and XML config
files.

Config files use Mitsuba's XML property syntax, so they read like the scene files::

    <training method="gr">
        <integer name="k" value="6"/>
        <float name="lambda_lap" value="8e-4"/>
        <boolean name="use_pga" value="true"/>
    </training>

``TrainConfig`` groups its fields into parts (``cfg.schedule``, ``cfg.deinit``,
``cfg.graph``, ``cfg.densify``, ``cfg.losses``, ``cfg.optim``, ``cfg.protocol``,
``cfg.run``), as gsplat groups its strategy's. Everything outside the code spells the
fields flat: config files, ``--option key=value``, the presets and the records of runs
(metrics.json, checkpoints). ``TrainConfig.from_flat`` / ``to_flat`` map between the two.

Every key must be a field of one of the parts (unknown or misspelled keys are an error,
with a suggestion) and the tag must match the field's type. Fields that can be chosen
automatically (``AUTO_FIELDS``) take ``value="none"`` (or are left out) for that, as does
``time_budget`` for "no budget". Command-line ``--option key=value`` pairs override the
file, which overrides the method preset, which overrides the defaults.
Defaults are the GR-Gaussian paper's (Sec. 4.1.2) in R2-Gaussian's normalised units
(volume in [-1, 1]^3).
"""
from __future__ import annotations

import difflib
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, fields

from mi_grg.protocol.early_stop import KEEP_STATES, STOP_RULE

#: Fields whose None means "automatic" (each field's comment says what is chosen). Records
#: written before they were optional spell that 0
#: (``mi_grg.training.checkpoint.upgrade_config_dict``).
AUTO_FIELDS = ("iterations", "horizon", "extent", "graph_s", "tv_extent", "log_3d_every",
               "checkpoint_every")

#: Fields that cannot change a run's result (when its checkpoints are written): a resume
#: may change them, and a finished run is not stale for them
#: (``mi_grg.lab.staleness.stale_keys``).
BOOKKEEPING = ("checkpoint_every", "frozen_step")

#: Fields that act only after training (on the returned state): a resume may change them,
#: since no checkpointed state depends on them, but a finished run is stale for them.
AFTER_TRAINING = ("refine", "refine_lam", "refine_max_iterations", "refine_output",
                  "refine_anchor", "refine_fall", "refine_tol", "fit_iterations", "fit_rate_scale",
                  "voxel_average", "field_blur")

# Method presets: R2-Gaussian is GR-Gaussian with every graph component switched off, and
# without the TV refinement (gr's addition beyond the paper; the baseline stays R2-Gaussian).
PRESETS = {
    "gr": {},
    "r2": {"sigma_d": 0.0, "use_pga": False, "use_graph_field": False, "lambda_lap": 0.0,
           "refine": "none", "voxel_average": 0.0},
}


#: The volumes De-Init can start from (``DeInit.init``).
INIT_VOLUMES = ("fdk", "pdhg")

#: A view's data term in training (``Losses.data_loss``): "l1", the paper's mean absolute
#: residual; "rms", the root mean square residual (least squares' direction, at a scale
#: that does not shrink with the residual, so the TV and graph weights keep their pull);
#: the keys of ``mi_grg.training.losses.DATA_TERMS``.
DATA_LOSSES = ("l1", "rms")

#: What runs after training (``Protocol.refine``): "none", or "tv": a data-consistent
#: total-variation refinement of the voxelised result whose weight and length the
#: held-out views choose (``mi_grg.training.result``).
REFINE_MODES = ("none", "tv")

#: What a refined run exports (``Protocol.refine_output``): "gaussians", the refined volume
#: fitted back into the Gaussians (what is exported is what is scored), or "voxels", the
#: refined grid itself as vol_pred, the Gaussians before it exported under another name.
REFINE_OUTPUTS = ("gaussians", "voxels")

#: The refinement's data (``Protocol.refine_anchor``): "on", anchored on the field's own
#: projections; "off", the measured projections; "auto", the measured ones where
#: densification did not meet the field's demand, else whichever of the two reaches the
#: lower held-out residual (``mi_grg.training.result``).
REFINE_ANCHORS = ("auto", "on", "off")

#: A blur of the returned field beyond the voxel average (``Protocol.field_blur``):
#: "heldout", the share of a voxel's box variance whose blur of the kept state fits the
#: held-out views best (``mi_grg.training.result.field_share``); "none", no blur.
FIELD_BLURS = ("heldout", "none")

#: Training's truncation extent (std devs) when ``Schedule.extent`` is None: the
#: projector, the logged 3-D PSNR and the output volume use it. Shorter than the
#: projector's 4.5: its truncation error is a small fraction of the noise of sparse noisy
#: views, and it saves training time (docs/benchmarks.md, "Training step").
TRAIN_EXTENT = 3.5

#: Iterations at 64^3 (``trainer.iteration_rule``): about what the 5-minute target buys on
#: this project's 2-core CPU at extent 3.5 (docs/benchmarks.md, "The iteration rule
#: re-derived").
ITERATIONS_AT_64 = 3000


#: Today's rule, as metrics.json records it (``method_info.iteration_rule``).
ITERATION_RULE = "3000*sqrt(n/64) to 64, 3000*min(n/64,2) above"


def iterations_for_size(n: int) -> int:
    """Today's automatic iteration count for n = max(nVoxel) (``ITERATION_RULE``; why:
    ``mi_grg.training.trainer.iteration_rule``)."""
    if n <= 64:
        return max(500, int(round(ITERATIONS_AT_64 * math.sqrt(n / 64))))
    return int(round(ITERATIONS_AT_64 * min(n / 64, 2.0)))


@dataclass
class Schedule:
    """How long the run is and what it starts from."""
    iterations: int | None = None  # None: scaled to the problem size
                                   # (mi_grg.training.trainer.iteration_rule)
    horizon: int | None = None     # length of the schedule (learning-rate decay to
                                   # lr_final_ratio, densification window, held-out window,
                                   # evaluation interval); None: the rule's count for the
                                   # grid. A run shorter than it compresses the schedule into
                                   # its own length; a longer one follows it, then trains
                                   # every view at a rate that keeps decaying (so that more
                                   # iterations converge rather than stretch the early,
                                   # fast phase: docs/benchmarks.md, "More iterations")
    seed: int = 0                  # same seed, same run up to float atomics: the scatter-
                                   # adds sum in thread order, so volumes of two runs differ
                                   # slightly (docs/benchmarks.md)
    extent: float | None = None    # Gaussian support in std devs; None: TRAIN_EXTENT
                                   # (shorter than the projector's default 4.5)


@dataclass
class DeInit:
    """De-Init (Sec. 3.3.1): the first Gaussians, sampled from a denoised volume."""
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


@dataclass
class Graph:
    """The kNN graph (Sec. 3.2): the graph-augmented field and its Laplacian term."""
    use_graph_field: bool = True   # Eq. 10/13 graph-augmented density field
    k: int = 6                     # neighbours in the kNN graph
    graph_s: float | None = None   # weight scale s in exp(-d^2 / s); None: automatic
                                   # (mi_grg.training.graph.default_scale)
    rebuild_keeps_field: bool = False  # after densification, rescale the densities so that
                                   # the rebuilt graph alone does not change the field:
                                   # each kernel keeps its source's multiplier 1 + sum w
                                   # (why: mi_grg.training.trainer.carry_density_scale)
    lambda_lap: float = 8e-4       # graph Laplacian weight (raw sum x 50k / N, see train)


@dataclass
class Densification:
    """PGA densification (Sec. 3.3.2): the one set of its settings, which
    ``mi_grg.training.densify.PGADensifier`` reads as they are (gsplat's strategy
    dataclass). The window (densify_start/stop/interval, and the protocol's eval_every)
    is the paper's for 30k iterations; a run scales it to its length, and the cap to its
    grid, in the densifier's ``DensifyWindow`` (state, not settings)."""
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
    # R2-Gaussian's rules (its defaults):
    clone_scale_fraction: float = 0.1  # clone if max scale <= this x volume size, else split
    split_scale_factor: float = 1.6    # a split's children scales = parent / this
    min_density: float = 1e-5          # prune below (R2's density_min_threshold)
    bbox_margin: float = 0.0           # prune outside the bbox enlarged by this x its size


@dataclass
class Losses:
    """The projection loss (its data term and SSIM share) and the 3-D TV term on a random
    block."""
    data_loss: str = "l1"          # DATA_LOSSES
    lambda_ssim: float = 0.25
    lambda_tv: float = 0.05
    tv_block: int = 32             # edge of the randomly placed TV block, voxels
    tv_extent: float | None = 3.0  # Gaussian support in std devs inside the TV block;
                                   # None: ``extent``. 3 is the 3-sigma cut of 3DGS-style
                                   # rasterisers; it needs (3/4.5)^3 = 0.3x the voxel pairs
    tv_every: int = 2              # TV on every n-th iteration only, weighted n x lambda_tv:
                                   # the same expected gradient (the block is random anyway)
                                   # for 1/n of the TV cost (bench/train_step.py times it)


@dataclass
class Optim:
    """Adam's learning rates; each decays exponentially to lr_final_ratio of itself."""
    lr_position: float = 2e-4
    lr_density: float = 1e-2
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    lr_final_ratio: float = 0.1


@dataclass
class Protocol:
    """Early stopping without ground truth: held-out views, the stop rule, what is kept."""
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
    refine: str = "tv"             # after training: "tv" refines the field by TV-regularised
                                   # least squares (PDHG) anchored on the Gaussians' own
                                   # projections, its length chosen by the held-out
                                   # residual (mi_grg.training.result; why:
                                   # docs/benchmarks.md, "The field's result"); "none":
                                   # the field as trained (the paper, R2-Gaussian)
    refine_lam: float = 0.003      # the refinement's TV weight (PDHG's dimensionless lam)
    refine_max_iterations: int = 200  # cap on the refinement's length (the held-out
                                   # residual chooses within it; metrics say when it binds)
    refine_anchor: str = "auto"    # the refinement's data: "on" anchored on the field's
                                   # own projections, "off" the measured ones, "auto"
                                   # "off" where densification's demand was not met, else
                                   # the one with the lower held-out residual (why:
                                   # docs/benchmarks.md, "The refinement's anchor")
    refine_fall: float = 1.0       # the refinement stops where the held-out residual has
                                   # made this share of its fall from the start to its
                                   # minimum (1: at the minimum; why: docs/benchmarks.md,
                                   # "The refinement's weight and length")
    refine_tol: float = 0.005      # ... or where it is first within this share of its
                                   # minimum (0: at the minimum), whichever comes first
                                   # (why: docs/benchmarks.md, "The refinement's tolerance")
    refine_output: str = "gaussians"  # "gaussians": the refined volume is fitted back into
                                   # the Gaussians, vol_pred is their voxelisation;
                                   # "voxels": vol_pred is the refined grid
    fit_iterations: int = 150      # Adam steps of that fit (it stops early once it
                                   # matches the grid to mi_grg.training.distill.FIT_STOP_DB)
    fit_rate_scale: float = 2.0    # its Adam rates: the training's initial rates times
                                   # this. Why 150 at 2x: it scores as 300 steps at 1x did,
                                   # in half the time (docs/benchmarks.md, "The fit back")
    voxel_average: float = 0.5     # share of a voxel's box variance the returned field is
                                   # blurred by, so that voxelising it gives voxel averages
                                   # (mi_grg.core.voxel_average); 0: centre samples (paper)
                                   # (why 0.5: docs/benchmarks.md, "The voxel average's
                                   # strength")
    field_blur: str = "none"       # "heldout": the held-out views add the blur that fits
                                   # them best (the field's own noise); "none": no more
                                   # (why not the default: docs/benchmarks.md, "The voxel
                                   # average's strength")
    monitor_3d: bool = False       # RESEARCH ONLY: stop on 3-D PSNR vs ground truth instead
    log_3d_every: int | None = None  # log 3-D PSNR vs ground truth every n iterations
                                   # (no effect on training); None: at each held-out
                                   # evaluation


@dataclass
class Run:
    """When checkpoints are written, and a wall-clock budget for the whole training."""
    checkpoint_every: int | None = None  # iterations between checkpoints; None: a tenth
                                   # of the run, 1 to 500 (trainer.checkpoint_interval), so
                                   # that a short run has them too
    time_budget: float | None = None  # seconds for the whole training (De-Init to the
                                   # returned state): the iteration count and schedule are
                                   # planned from a probe of this machine's speed instead of
                                   # iteration_rule (mi_grg.training.budget); None: no budget
    frozen_step: bool = True       # record the iteration once with dr.freeze and replay
                                   # it (no Python tracing per iteration;
                                   # mi_grg.training.recording): the same results, less
                                   # host time, which is most of a GPU's iteration
                                   # (docs/benchmarks.md, "On a GPU"); false: traced


#: TrainConfig's parts: attribute -> part class. Field names are unique across the parts,
#: so that the flat keys (config files, --option, records) name one field each.
PARTS = {"schedule": Schedule, "deinit": DeInit, "graph": Graph, "densify": Densification,
         "losses": Losses, "optim": Optim, "protocol": Protocol, "run": Run}

#: Flat key -> (part attribute, dataclasses.Field), in the order files and records list them.
_FIELDS = {f.name: (part, f) for part, cls in PARTS.items() for f in fields(cls)}

#: Every flat key (config files, --option, metrics.json and checkpoint records).
FLAT_KEYS = tuple(_FIELDS)


@dataclass
class TrainConfig:
    """Every hyperparameter of GR-Gaussian / R2-Gaussian training, in named parts (read
    as ``cfg.losses.lambda_tv``). Files, options and records spell it flat (``lambda_tv``):
    ``from_flat`` and ``to_flat`` are the one mapping between the two."""

    schedule: Schedule = field(default_factory=Schedule)
    deinit: DeInit = field(default_factory=DeInit)
    graph: Graph = field(default_factory=Graph)
    densify: Densification = field(default_factory=Densification)
    losses: Losses = field(default_factory=Losses)
    optim: Optim = field(default_factory=Optim)
    protocol: Protocol = field(default_factory=Protocol)
    run: Run = field(default_factory=Run)

    @classmethod
    def from_flat(cls, values: dict) -> "TrainConfig":
        """The config of flat ``{key: value}`` (missing keys take their defaults); an
        unknown key is a ``ConfigError`` with a suggestion. Values are taken as given
        (``make_config`` coerces strings)."""
        parts = {part: {} for part in PARTS}
        for key, value in values.items():
            _check_key(key)
            parts[_FIELDS[key][0]][key] = value
        return cls(**{part: PARTS[part](**kw) for part, kw in parts.items()})

    def to_flat(self) -> dict:
        """Every field as flat ``{key: value}``, in ``FLAT_KEYS`` order."""
        return {key: getattr(getattr(self, part), key) for key, (part, _) in _FIELDS.items()}

    def __post_init__(self):
        _validate(self.to_flat())


def _validate(c: dict) -> None:
    """The checks of a flat config ``c``; each error names the key."""
    for key, v in c.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ConfigError(f"{key} must be finite, got {v}")
    if c["time_budget"] is not None:
        if not c["time_budget"] > 0:
            raise ConfigError(f"time_budget must be > 0 seconds (or none: no budget), "
                              f"got {c['time_budget']!r}")
        if c["iterations"] is not None:
            raise ConfigError(f"time_budget ({c['time_budget']:g} s) plans the iteration "
                              f"count; iterations={c['iterations']} would override it: "
                              "give one of them")
    for name in AUTO_FIELDS:
        v = c[name]
        if v is not None and not v > 0:
            raise ConfigError(f"{name} must be > 0 or none (automatic), got {v!r}; "
                              "0 no longer means automatic: write none or leave it out")
    nonneg = [k for k, v in c.items() if _base_type(_FIELDS[k][1]) in ("int", "float")
              and v is not None and v < 0]
    if nonneg:
        raise ConfigError(f"must be >= 0: {', '.join(nonneg)}")
    if not c["split_scale_factor"] > 0:
        raise ConfigError(f"split_scale_factor must be > 0, got {c['split_scale_factor']}")
    if c["k"] < 1:
        raise ConfigError("k must be >= 1")
    if not 0 < c["lr_final_ratio"] <= 1:
        raise ConfigError("lr_final_ratio must be in (0, 1]")
    if c["n_points"] < 1:
        raise ConfigError("n_points must be >= 1")
    if not 0.0 <= c["holdout_until"] <= 1.0:
        raise ConfigError(f"holdout_until must be a fraction in [0, 1], got "
                          f"{c['holdout_until']}")
    if c["init"] not in INIT_VOLUMES:
        raise ConfigError(f"init must be one of {', '.join(INIT_VOLUMES)}, got "
                          f"{c['init']!r}")
    if c["data_loss"] not in DATA_LOSSES:
        raise ConfigError(f"data_loss must be one of {', '.join(DATA_LOSSES)}, got "
                          f"{c['data_loss']!r}")
    if c["refine"] not in REFINE_MODES:
        raise ConfigError(f"refine must be one of {', '.join(REFINE_MODES)}, got "
                          f"{c['refine']!r}")
    if c["refine_anchor"] not in REFINE_ANCHORS:
        raise ConfigError(f"refine_anchor must be one of {', '.join(REFINE_ANCHORS)}, got "
                          f"{c['refine_anchor']!r}")
    if c["refine_output"] not in REFINE_OUTPUTS:
        raise ConfigError(f"refine_output must be one of {', '.join(REFINE_OUTPUTS)}, got "
                          f"{c['refine_output']!r}")
    if not c["refine_lam"] > 0:
        raise ConfigError(f"refine_lam must be > 0, got {c['refine_lam']}")
    if c["refine_max_iterations"] < 1:
        raise ConfigError("refine_max_iterations must be >= 1")
    if not 0.0 < c["refine_fall"] <= 1.0:
        raise ConfigError(f"refine_fall must be a share in (0, 1], got {c['refine_fall']}")
    if not 0.0 <= c["refine_tol"] < 1.0:
        raise ConfigError(f"refine_tol must be a share in [0, 1), got {c['refine_tol']}")
    if not 0.0 < c["fit_rate_scale"] < math.inf:
        raise ConfigError(f"fit_rate_scale must be a finite factor > 0, got "
                          f"{c['fit_rate_scale']}")
    if c["field_blur"] not in FIELD_BLURS:
        raise ConfigError(f"field_blur must be one of {', '.join(FIELD_BLURS)}, got "
                          f"{c['field_blur']!r}")
    if not c["voxel_average"] <= 1.0:
        raise ConfigError(f"voxel_average must be a fraction in [0, 1], got "
                          f"{c['voxel_average']}")
    if c["keep_state"] not in KEEP_STATES:
        raise ConfigError(f"keep_state must be one of {', '.join(KEEP_STATES)}, "
                          f"got {c['keep_state']!r}")
    zero = [n for n in ("eval_every", "densify_interval", "tv_every",
                        "stop_patience", "max_gaussians") if c[n] < 1]
    if zero:
        raise ConfigError(f"must be >= 1 (iterations or evaluations): {', '.join(zero)}")


class ConfigError(ValueError):
    """An invalid or unknown configuration key; the message names it."""


def _base_type(f) -> str:
    """A field's type without "| None" ("int", "float", "bool" or "str")."""
    return f.type.replace(" | None", "")
_TAG_OF_TYPE = {"int": "integer", "float": "float", "bool": "boolean", "str": "string"}
_NONE_WORDS = ("none", "null")


def _check_key(key: str) -> None:
    if key not in _FIELDS:
        close = difflib.get_close_matches(key, list(_FIELDS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"unknown training option {key!r}{hint}")


def _coerce(key: str, value):
    _check_key(key)
    f = _FIELDS[key][1]
    kind = _base_type(f)
    if "| None" in f.type and (value is None or (
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
    from mi_grg.data.inputs import InputError, check_xml
    try:
        check_xml(path, "training config")    # bounded before the tree is built
        root = ET.parse(path).getroot()
    except InputError as e:
        raise ConfigError(f"cannot read config {e}") from None
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
        try:
            _check_key(name)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None
        kind = _base_type(_FIELDS[name][1])
        want = _TAG_OF_TYPE[kind]
        if el.tag != want:
            raise ConfigError(f"{path}: {name} is a {kind}; write <{want} "
                              f"name=\"{name}\" .../>, not <{el.tag}>")
        if name in values:
            raise ConfigError(f"{path}: {name} is given twice")
        try:
            values[name] = _coerce(name, value)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None
    return method, values


def write_config_xml(config: TrainConfig, path, method: str | None = None) -> None:
    """Write every field of ``config`` (a complete, self-documenting config file); a field
    left automatic is written as value="none"."""
    method_attr = f' method="{method}"' if method else ""
    lines = [f'<training version="1"{method_attr}>']
    for key, v in config.to_flat().items():
        text = ("none" if v is None else str(v).lower() if isinstance(v, bool)
                else v if isinstance(v, str) else repr(v))
        tag = _TAG_OF_TYPE[_base_type(_FIELDS[key][1])]
        lines.append(f'    <{tag} name="{key}" value="{text}"/>')
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
    try:
        return TrainConfig.from_flat(values)
    except ConfigError as e:   # a value the file set: the file is named
        if path is None or not any(k in str(e) for k in set(file_values) - set(overrides)):
            raise
        raise ConfigError(f"{path}: {e}") from None
