"""Experiment suites: the JSON file of simulated cases (``load_suite``), its validation
(``SuiteError`` names the field), and the names of the paper's experiments and methods.
The suite format is described in experiments/README.md."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

EXPERIMENTS = ("table1", "table2", "table3", "iterations", "speed", "views", "seeds")
#: Keys each experiment's block in a suite may set (anything else is an error).
EXPERIMENT_KEYS = {"table1": ("methods", "cases"), "table2": ("cases",),
                   "table3": ("k", "sigma_d", "cases"),
                   "iterations": ("methods", "log_3d_every", "cases"),
                   "speed": ("methods", "cases"), "views": ("views", "methods", "cases"),
                   "seeds": ("seeds", "methods", "cases")}
ALL_METHODS = ("fdk", "sart", "asd-pocs", "pdhg", "r2", "gr")
CATEGORIES = {"HO": "human organs / organ-like", "BS": "biological specimens",
              "AO": "artificial objects"}
CASE_FIELDS = ("name", "category", "source", "views", "test_views", "n", "det", "mode",
               "noise", "seed")
TRAINED = ("r2", "gr")               # methods configured by mi_grg.training.config.TrainConfig
CURVE_METHODS = {"sart": "sart-curve", "asd-pocs": "asd-pocs-curve", "pdhg": "pdhg-curve"}
#: Table 1's second row for the iterative classical methods: the paper's fixed sweep count
#: (their default stops on held-out views, mi_grg.protocol.heldout).
FIXED_ROWS = {"sart": {"n_iter": 10, "stop": "none"},
              "asd-pocs": {"n_iter": 10, "stop": "none"}}
#: Table 1's extra rows per method, one per weight rule besides the method's default (PDHG's
#: and ASD-POCS's: the one-standard-error rule): run name, options, label. gr is measured
#: against the best of every rule on each case.
RULE_ROWS = {"pdhg": (("pdhg-best", {"lam_rule": "best"},
                       "pdhg (TV weight by the best held-out PSNR)"),
                      ("pdhg-morozov", {"lam_rule": "morozov"},
                       "pdhg (TV weight by Morozov's rule)")),
             "asd-pocs": (("asd-pocs-best", {"alpha_rule": "best"},
                           "asd-pocs (TV weight by the best held-out PSNR)"),)}
#: gr's classical step alone (Table 1 shows a hybrid's parts): PDHG from zero at gr's
#: refinement weight for five times the refinement's iteration cap, run name and label.
COLD_ROW = ("pdhg-cold", "pdhg (from zero at gr's refinement weight, to convergence)")
COLD_FACTOR = 5
NOSTOP_DROP = 0.99                   # stop_drop that never triggers (iteration analysis)


class SuiteError(ValueError):
    """An invalid suite file; the message names the field."""


@dataclass(frozen=True)
class CaseSpec:
    """One simulated scan (all sizes in voxels / pixels; noise as NoiseModel fields)."""
    name: str
    category: str
    source: str                 # phantom name (mi_grg.data.phantoms) or a .npy volume
    views: int
    test_views: int
    n: int
    det: int
    mode: str = "cone"
    noise: dict | None = None
    seed: int = 0
    oversample: float = 4.0     # volume sources: samples per source voxel (volume_phantom)
    ground_truth: str = "average"   # volume sources: "average" | "block"
    data_name: str = ""         # directory under OUT/data ("" -> name)

    @property
    def data_dir_name(self) -> str:
        return self.data_name or self.name

    @property
    def is_volume(self) -> bool:
        return self.source.endswith(".npy")

    def key(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("data_name")
        d.pop("category")
        if not self.is_volume:
            d.pop("oversample")
            d.pop("ground_truth")
        return d


@dataclass
class Suite:
    name: str
    path: str
    variant: str
    cases: list
    method_options: dict = field(default_factory=dict)
    experiments: dict = field(default_factory=dict)
    extra_methods: dict = field(default_factory=dict)
    description: str = ""

    def case(self, name: str) -> CaseSpec:
        for c in self.cases:
            if c.name == name:
                return c
        raise SuiteError(f"suite {self.path} has no case {name!r}; cases: "
                         f"{[c.name for c in self.cases]}")


def _int_field(c: dict, key: str, where: str, minimum: int) -> int:
    v = c[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise SuiteError(f"{where}.{key} must be an integer >= {minimum}, got {v!r}")
    return v


def _case_spec(c, where: str, seen: set) -> CaseSpec:
    """One validated case of a suite (``where`` names it in errors; ``seen``: the names
    of the cases before it)."""
    from mi_grg.data.phantoms import PHANTOMS
    known = {f.name for f in dataclasses.fields(CaseSpec)} - {"data_name"}
    if not isinstance(c, dict):
        raise SuiteError(f"{where} must be an object")
    missing = [k for k in CASE_FIELDS if k not in c]
    if missing:
        raise SuiteError(f"{where} lacks {missing}")
    unknown = sorted(set(c) - known)
    if unknown:
        raise SuiteError(f"{where} has unknown field(s) {unknown}; known: {sorted(known)}")
    name = c["name"]
    if not isinstance(name, str) or not name or any(ch in name for ch in "/\\ ") \
            or name == "data":
        raise SuiteError(f"{where}.name must be a non-empty name without / \\ or spaces "
                         f"(and not 'data'), got {name!r}")
    if name in seen:
        raise SuiteError(f"{where}: duplicate case name {name!r}")
    if not isinstance(c["category"], str) or c["category"] not in CATEGORIES:
        raise SuiteError(f"{where}.category must be one of {list(CATEGORIES)}, got "
                         f"{c['category']!r}")
    src = c["source"]
    if not isinstance(src, str) or not (src in PHANTOMS or src.endswith(".npy")):
        raise SuiteError(f"{where}.source must be a phantom {PHANTOMS} or a .npy volume, "
                         f"got {src!r}")
    if not isinstance(c["mode"], str) or c["mode"] not in ("cone", "parallel"):
        raise SuiteError(f"{where}.mode must be 'cone' or 'parallel', got {c['mode']!r}")
    noise = c["noise"]
    if noise is not None:
        if not isinstance(noise, dict):
            raise SuiteError(f"{where}.noise must be null or {{I0, electronic_std}}")
        from mi_grg.data.noise import NoiseModel
        try:
            NoiseModel(**noise)
        except (TypeError, ValueError) as e:
            raise SuiteError(f"{where}.noise: {e}") from None
    over, truth = c.get("oversample", 4.0), c.get("ground_truth", "average")
    if isinstance(over, bool) or not isinstance(over, (int, float)) or not over > 0:
        raise SuiteError(f"{where}.oversample must be a number > 0, got {over!r}"[:300])
    if truth not in ("average", "block"):
        raise SuiteError(f"{where}.ground_truth must be 'average' or 'block', got "
                         f"{truth!r}"[:300])
    return CaseSpec(name=name, category=c["category"], source=src,
                    views=_int_field(c, "views", where, 2),
                    test_views=_int_field(c, "test_views", where, 0),
                    n=_int_field(c, "n", where, 2), det=_int_field(c, "det", where, 2),
                    mode=c["mode"], noise=noise, seed=_int_field(c, "seed", where, 0),
                    oversample=float(over), ground_truth=truth)


#: The keys a suite file may have (anything else is an error with the closest key named).
SUITE_KEYS = ("name", "description", "variant", "cases", "method_options", "experiments",
              "extra_methods")


def _unknown(names, known, where: str) -> None:
    """SuiteError naming each of ``names`` not in ``known``, with the closest known one."""
    from mi_grg.data.scene import suggest
    bad = [n for n in names if n not in known]
    if bad:
        hints = "; ".join(f"{str(n)[:80]!r}{suggest(str(n), known)}" for n in bad)
        raise SuiteError(f"{where}: unknown key(s) {hints}; known: {list(known)}")


def _check_method_options(mo: dict, extra: dict, path) -> None:
    """method_options names methods that exist and options that they take."""
    import inspect
    from mi_grg.training.config import FLAT_KEYS
    _unknown(mo, (*ALL_METHODS, *extra), f"{path}: method_options")
    for method, options in mo.items():
        if method in TRAINED:
            known = (*FLAT_KEYS, "config", "progress", "resume")
        elif method in ALL_METHODS:
            from mi_grg.methods import get_method
            params = inspect.signature(get_method(method)).parameters
            known = tuple(k for k in params if k not in ("case", "out_dir"))
        else:
            continue              # an extra method: it checks its own options
        _unknown(options, known, f"{path}: method_options.{method}")


#: What each value of an experiment's block must be: (a list?, of what type, said how).
_BLOCK_TYPES = {"methods": (True, str, "a list of method names"),
                "cases": (True, str, "a list of case names"),
                "k": (True, int, "a list of integers"),
                "sigma_d": (True, (int, float), "a list of numbers"),
                "views": (True, int, "a list of integers"),
                "seeds": (True, int, "a list of integers"),
                "log_3d_every": (False, int, "an integer")}


def _check_experiment(ename: str, cfg, seen: set, where: str) -> None:
    """An experiment's block: known keys, values of the right types, known cases."""
    if cfg is not None and not isinstance(cfg, dict):
        raise SuiteError(f"{where} must be an object")
    unknown = sorted(set(cfg or {}) - set(EXPERIMENT_KEYS[ename]))
    if unknown:
        raise SuiteError(f"{where} has unknown key(s) {unknown}; known: "
                         f"{list(EXPERIMENT_KEYS[ename])}")
    for key, value in (cfg or {}).items():
        listed, kind, said = _BLOCK_TYPES[key]
        items = value if listed and isinstance(value, list) else [value]
        if (listed and not isinstance(value, list)) or not all(
                isinstance(v, kind) and not isinstance(v, bool) for v in items):
            raise SuiteError(f"{where}.{key} must be {said}, got {value!r}"[:300])
    for cname in (cfg or {}).get("cases") or []:
        if cname not in seen:
            raise SuiteError(f"{where}.cases names unknown case {cname!r}")


def load_suite(path) -> Suite:
    """Read and validate a suite JSON file (see experiments/README.md for the format)."""
    from mi_grg.data.inputs import InputError, read_json
    path = Path(path)
    try:
        raw = read_json(path, "suite")
    except InputError as e:
        raise SuiteError(str(e)) from None
    except OSError as e:
        raise SuiteError(f"cannot read suite {path}: {e}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("cases"), list) or not raw["cases"]:
        raise SuiteError(f"{path}: expected an object with a non-empty 'cases' list")
    _unknown(raw, SUITE_KEYS, str(path))
    cases, seen = [], set()
    for i, c in enumerate(raw["cases"]):
        spec = _case_spec(c, f"{path}: cases[{i}]", seen)
        seen.add(spec.name)
        cases.append(spec)
    mo = raw.get("method_options", {}) or {}
    if not isinstance(mo, dict) or not all(isinstance(v, dict) for v in mo.values()):
        raise SuiteError(f"{path}: method_options must map method names to option objects")
    ex = raw.get("experiments", {}) or {}
    if not isinstance(ex, dict):
        raise SuiteError(f"{path}: experiments must map experiment names to objects")
    bad = sorted(set(ex) - set(EXPERIMENTS))
    if bad:
        raise SuiteError(f"{path}: unknown experiment(s) {bad}; known: {list(EXPERIMENTS)}")
    for ename, cfg in ex.items():
        _check_experiment(ename, cfg, seen, f"{path}: experiments.{ename}")
    extra = raw.get("extra_methods", {}) or {}
    if not isinstance(extra, dict) or not all(isinstance(v, str) and ":" in v
                                              for v in extra.values()):
        raise SuiteError(f"{path}: extra_methods must map names to 'module:function'")
    _check_method_options(mo, extra, path)
    return Suite(name=str(raw.get("name", path.stem)), path=str(path),
                 variant=str(raw.get("variant", "llvm_ad_mono")), cases=cases,
                 method_options=mo, experiments=ex, extra_methods=extra,
                 description=str(raw.get("description", "")))

