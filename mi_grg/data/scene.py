"""A CT scan described by one Mitsuba scene XML file (``scenes/*.xml``).

The file names (schema in ``docs/conventions.md``):

* ``<sensor type="ct_scanner">``: the scanner (TIGRE/R2-Gaussian fields, the angles, the
  held-out test views and the noise model); the plugin is ``plugins/ct_scanner.py``.
* inside it, one ``<medium>``: what is scanned, e.g.
  ``<medium type="ct_phantom"><string name="phantom" value="shepp"/></medium>``.
* optionally ``<integrator type=...>`` and further objects (e.g. a constant emitter for a
  ``volpath`` cross-check).

``load_scan`` turns the file into a :class:`Scan` (plain Python values, with CLI overrides);
``load_mitsuba_scene`` loads it with Mitsuba; ``write_scan_xml`` writes a ``Scan`` back.
The sensor plugin parses its fields with ``parse_scanner_fields`` below, and ``load_scan``
takes the geometry from the instantiated sensor, so the XML means one thing on either path.
"""
from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from mi_grg.core.geometry import Geometry, circular_angles


class ScanError(ValueError):
    """An invalid scene file or scanner field; the message names the field."""


# ---------------------------------------------------------------- the scanner fields
#: Every property of ``<sensor type="ct_scanner">``: name -> (XML tag, unit and meaning).
SCANNER_FIELDS = {
    "mode": ("string", "cone | parallel"),
    "DSD": ("float", "distance source -> detector centre (length unit of the scan)"),
    "DSO": ("float", "distance source -> rotation axis (length)"),
    "nDetector": ("string", "detector pixels 'v u' (rows, columns)"),
    "sDetector": ("string", "detector size 'v u' (whole detector, length)"),
    "nVoxel": ("string", "volume voxels 'x y z'"),
    "sVoxel": ("string", "volume size 'x y z' (whole volume, length)"),
    "offOrigin": ("string", "volume centre offset 'x y z' (length), default '0 0 0'"),
    "offDetector": ("string", "detector centre offset 'v u' along (e_v, e_u) (length), "
                              "default '0 0'"),
    "views": ("integer", "number of training views, equally spaced (or give angles)"),
    "total_angle": ("float", "arc covered by the views, DEGREES, default 360 (with views)"),
    "start_angle": ("float", "angle of the first view, DEGREES, default 0 (with views)"),
    "angles": ("string", "training angles, RADIANS, comma or space separated "
                         "(instead of views)"),
    "test_views": ("integer", "held-out test views, default 0; placed half a step after the "
                              "training grid over the same arc"),
    "test_angles": ("string", "test angles, RADIANS (instead of test_views)"),
    "vectors": ("string", "per-view scan: 12 numbers per training view (ASTRA cone_vec / "
                          "parallel3d_vec: source or ray, detector centre, u step, v step; "
                          "length), rows separated by ';', in the order of the angles"),
    "test_vectors": ("string", "per-view scan: 12 numbers per test view (with vectors)"),
    "noise": ("string", "none | poisson+gaussian, default none (applies to training views)"),
    "I0": ("float", "photons per detector pixel of the unattenuated beam, default 1e4 "
                    "(poisson+gaussian only)"),
    "electronic_std": ("float", "std of the Gaussian electronic noise in photon counts, "
                                "default 10 (poisson+gaussian only)"),
    "noise_seed": ("integer", "seed of the noise draws, default 0 (poisson+gaussian only)"),
    "clip_negative": ("boolean", "set negative noisy line integrals to 0, as R2-Gaussian "
                                 "does; default true (poisson+gaussian only)"),
}
NOISE_FIELDS = ("I0", "electronic_std", "noise_seed", "clip_negative")
REQUIRED = ("mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel")
NOISE_MODELS = ("none", "poisson+gaussian")
DEFAULT_I0 = 1e4
DEFAULT_ELECTRONIC_STD = 10.0
_FULL_CIRCLE_DEG = 360.0


def suggest(name: str, choices) -> str:
    """' (did you mean 'x'?)' for a near miss, else ''."""
    close = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.6)
    if not close:  # case slips (dsd -> DSD) score low with difflib
        close = [c for c in choices if c.lower() == name.lower()]
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_field_names(names, allowed=SCANNER_FIELDS, where="ct_scanner") -> None:
    """Raise ``ScanError`` for any name not in ``allowed``, with a did-you-mean hint."""
    unknown = [n for n in names if n not in allowed]
    if unknown:
        hints = "; ".join(f"{n!r}{suggest(n, allowed)}" for n in unknown)
        raise ScanError(f"{where}: unknown parameter(s) {hints}. Known: {sorted(allowed)}")


def _number(name, value) -> float:
    if isinstance(value, bool):
        raise ScanError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ScanError(f"{name} must be a number, got {value!r}") from None


def _numbers(name, value) -> np.ndarray:
    """A list of numbers from a string ('1 2', '1, 2') or a sequence; float64, 1-D."""
    if isinstance(value, str):
        parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
        try:
            return np.array([float(p) for p in parts], dtype=np.float64)
        except ValueError:
            raise ScanError(f"{name} must be numbers separated by spaces or commas, "
                            f"got {value!r}") from None
    try:
        return np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ScanError(f"{name} must be a list of numbers, got {value!r}") from None


def _tuple(name, value) -> tuple:
    return tuple(_numbers(name, value).tolist())  # plain floats: readable error messages


def _count(name, value, minimum) -> int:
    x = _number(name, value)
    if not math.isfinite(x) or x != round(x) or x < minimum:
        raise ScanError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(x)


def _degrees(name, value, default, low, high) -> float:
    """An angle field in degrees -> radians; 360 maps to exactly 2 pi."""
    x = default if value is None else _number(name, value)
    if not (math.isfinite(x) and low <= x <= high):
        raise ScanError(f"{name} is in DEGREES and must lie in [{low}, {high}], got {value!r}")
    if x == _FULL_CIRCLE_DEG:
        return 2 * np.pi
    return math.radians(x)


def _exclusive(fields, a, b_group) -> None:
    given = [k for k in b_group if k in fields]
    if a in fields and given:
        raise ScanError(f"give either {a} or {'/'.join(b_group)}, not both "
                        f"(the scene sets {a} and {', '.join(given)})")


def parse_scanner_fields(fields: dict):
    """The scanner fields (XML names, see ``SCANNER_FIELDS``) -> (geometry, test_angles, noise).

    Values may be XML-typed Python values (str, int, float) or sequences. Returns the
    ``Geometry`` with the training angles (radians), the test angles [view] (radians, maybe
    empty) and the noise model (``None`` or ``{"model", "I0", "electronic_std", "seed",
    "clip_negative"}``).
    Raises ``ScanError``/``GeometryError`` naming the offending field.
    """
    check_field_names(fields)
    missing = [k for k in REQUIRED if k not in fields]
    if missing:
        raise ScanError(f"ct_scanner lacks required field(s) {missing}")
    mode = fields["mode"]
    if not isinstance(mode, str):
        raise ScanError(f"mode must be a string (cone | parallel), got {mode!r}")

    # training angles: views (+ arc in degrees) or explicit radians
    _exclusive(fields, "angles", ("views", "total_angle", "start_angle"))
    total = _degrees("total_angle", fields.get("total_angle"), _FULL_CIRCLE_DEG, 1e-9, 360.0)
    start = _degrees("start_angle", fields.get("start_angle"), 0.0, -360.0, 360.0)
    if "angles" in fields:
        angles = _numbers("angles", fields["angles"])
    elif "views" in fields:
        angles = circular_angles(_count("views", fields["views"], 1), total, start)
    else:
        raise ScanError("ct_scanner needs the training angles: views (a count) or "
                        "angles (radians)")

    _exclusive(fields, "test_angles", ("test_views",))
    if "test_angles" in fields:
        test_angles = _numbers("test_angles", fields["test_angles"])
        if not np.all(np.isfinite(test_angles)):
            raise ScanError(f"test_angles must be finite (radians), got {fields['test_angles']!r}")
    else:
        n_test = _count("test_views", fields.get("test_views", 0), 0)
        # half a step after the training grid, so no test view repeats a training view
        test_angles = (circular_angles(n_test, total, start) + total / (2 * n_test)
                       if n_test else np.zeros(0))

    geometry = Geometry(
        mode=mode, DSD=_number("DSD", fields["DSD"]), DSO=_number("DSO", fields["DSO"]),
        nDetector=_tuple("nDetector", fields["nDetector"]),
        sDetector=_tuple("sDetector", fields["sDetector"]),
        nVoxel=_tuple("nVoxel", fields["nVoxel"]),
        sVoxel=_tuple("sVoxel", fields["sVoxel"]),
        offOrigin=_tuple("offOrigin", fields.get("offOrigin", "0 0 0")),
        offDetector=_tuple("offDetector", fields.get("offDetector", "0 0")),
        angles=angles)
    return _with_vectors(geometry, fields, test_angles), test_angles, _parse_noise(fields)


def _rows(name, value, n) -> np.ndarray:
    """``n`` rows of 12 numbers from a field (rows separated by ';')."""
    text = value.replace(";", " ") if isinstance(value, str) else value
    flat = _numbers(name, text)
    if flat.size != 12 * n:
        raise ScanError(f"{name} must hold 12 numbers per view ({n} views: {12 * n}), got "
                        f"{flat.size}")
    return flat.reshape(n, 12)


def _with_vectors(geometry: Geometry, fields: dict, test_angles) -> Geometry:
    """The geometry with the scene's per-view vectors (training and test views), if any."""
    if "vectors" not in fields:
        if "test_vectors" in fields:
            raise ScanError("test_vectors needs vectors (the training views' rows)")
        return geometry
    if len(test_angles) and "test_vectors" not in fields:
        raise ScanError("a per-view scan with test views needs test_vectors too")
    rows = _rows("vectors", fields["vectors"], geometry.n_views)
    if len(test_angles):
        rows = np.concatenate([rows, _rows("test_vectors", fields["test_vectors"], len(test_angles))])
    return geometry.replace(vectors=rows, vector_angles=np.concatenate(
        [geometry.angles, np.asarray(test_angles, np.float64)]))


def _parse_noise(fields):
    model = fields.get("noise", "none")
    if model not in NOISE_MODELS:
        raise ScanError(f"noise must be one of {NOISE_MODELS}, got {model!r}"
                        f"{suggest(str(model), NOISE_MODELS)}")
    if model == "none":
        extra = [k for k in NOISE_FIELDS if k in fields]
        if extra:
            verb = "apply" if len(extra) > 1 else "applies"
            raise ScanError(f"{' and '.join(extra)} only {verb} with noise='poisson+gaussian' "
                            "(this scene has noise='none'); set noise or remove them")
        return None
    i0 = _number("I0", fields.get("I0", DEFAULT_I0))
    if not (math.isfinite(i0) and i0 > 0):
        raise ScanError(f"I0 (photons per pixel) must be finite and > 0, got {i0!r}")
    std = _number("electronic_std", fields.get("electronic_std", DEFAULT_ELECTRONIC_STD))
    if not (math.isfinite(std) and std >= 0):
        raise ScanError(f"electronic_std (photon counts) must be finite and >= 0, got {std!r}")
    seed = _count("noise_seed", fields.get("noise_seed", 0), 0)
    clip = fields.get("clip_negative", True)
    if isinstance(clip, str) and clip.lower() in ("true", "false"):
        clip = clip.lower() == "true"
    if not isinstance(clip, (bool, np.bool_)):
        raise ScanError(f"clip_negative must be a boolean (true | false), got {clip!r}")
    return {"model": model, "I0": i0, "electronic_std": std, "seed": seed,
            "clip_negative": bool(clip)}


# ---------------------------------------------------------------- the scan
@dataclass
class Scan:
    """Everything a scene file asks for, as plain Python values.

    Attributes:
        geometry:    scan geometry with the training angles (radians).
        test_angles: held-out test angles [view] (radians), maybe empty.
        noise:       ``None`` or ``{"model": "poisson+gaussian", "I0": photons per pixel,
                     "electronic_std": counts, "seed": noise seed, "clip_negative": bool}``
                     (training views only).
        object:      what is scanned, the ``<medium>`` of the ct_scanner sensor, as
                     ``{"type": plugin, **properties}`` (e.g. ``{"type": "ct_phantom",
                     "phantom": "shepp"}``; nested objects as nested dicts); ``{}`` if none.
        integrator:  ``{"type": plugin, **properties}``; ``{}`` when the scene names none.
        path:        the scene file (``None`` for a scan built in memory).
        other:       further top-level objects (e.g. the ``constant`` emitter of a volpath
                     cross-check), each ``{"type": plugin, **properties}``.
    """

    geometry: Geometry
    test_angles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    noise: dict | None = None
    object: dict = field(default_factory=dict)
    integrator: dict = field(default_factory=dict)
    path: str | None = None
    other: list = field(default_factory=list)

    def __post_init__(self):
        if self.noise:   # the scene file's defaults, so that equal scans compare equal
            self.noise = {"seed": 0, "clip_negative": True, **self.noise}

    def info(self) -> dict:
        """JSON-ready dict of everything the scene asks for (echoed into metrics.json)."""
        return {
            "scene": None if self.path is None else str(self.path),
            "scanner": self.geometry.to_scanner_dict(),
            "angles": [float(a) for a in self.geometry.angles],
            "test_angles": [float(a) for a in self.test_angles],
            "noise": dict(self.noise) if self.noise else {"model": "none"},
            "object": _jsonable(self.object),
            "integrator": _jsonable(self.integrator),
            "other": [_jsonable(o) for o in self.other],
        }


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (bool, int, float, str)) or d is None:
        return d
    try:
        return [float(x) for x in d]
    except TypeError:
        return str(d)


# ---------------------------------------------------------------- reading
_TAGS = {}  # plugin type -> XML tag, learnt from parsed files (Python plugins included)


def _tag_name(object_type) -> str | None:
    import mitsuba as mi
    T = mi.ObjectType
    return {T.Medium: "medium", T.Shape: "shape", T.Integrator: "integrator",
            T.Volume: "volume", T.BSDF: "bsdf", T.Emitter: "emitter", T.Sampler: "sampler",
            T.Texture: "texture", T.PhaseFunction: "phase", T.Film: "film",
            T.ReconstructionFilter: "rfilter", T.Sensor: "sensor"}.get(object_type)


def _children(state, index):
    """(property name, node index) of the objects nested in / referenced by a node."""
    import mitsuba as mi
    props = state.nodes[index].props
    T = mi.Properties.Type
    for name in props.keys():
        kind = props.type(name)
        if kind == T.ResolvedReference:
            yield name, props[name].index()
        elif kind == T.Reference:
            yield name, state.id_to_index[props[name].id()]


def _node_dict(state, index) -> dict:
    """A scene node as {"type": plugin, property: value, child name: nested dict}."""
    import mitsuba as mi
    node = state.nodes[index]
    props = node.props
    tag = _tag_name(node.type)
    if tag is not None:
        _TAGS[props.plugin_name()] = tag
    out = {"type": props.plugin_name()}
    children = dict(_children(state, index))
    for name in props.keys():
        if name in children:
            out[name] = _node_dict(state, children[name])
        elif props.type(name) == mi.Properties.Type.Object:
            out[name] = str(props[name])
        else:
            out[name] = props[name]
    return out


OVERRIDE_GROUPS = {  # an override replaces the XML fields that say the same thing otherwise
    "views": ("angles",), "total_angle": ("angles",), "start_angle": ("angles",),
    "angles": ("views", "total_angle", "start_angle"),
    "test_views": ("test_angles",), "test_angles": ("test_views",),
}


def apply_overrides(fields: dict, overrides: dict | None) -> dict:
    """Scanner fields with ``overrides`` applied (see ``load_scan``); a new dict."""
    fields = dict(fields)
    if not overrides:
        return fields
    check_field_names(overrides, where="override")
    for key, value in overrides.items():
        for other in OVERRIDE_GROUPS.get(key, ()):
            fields.pop(other, None)
        if key == "noise" and value == "none":
            for k in NOISE_FIELDS:
                fields.pop(k, None)
        if value is None:
            fields.pop(key, None)
        else:
            fields[key] = value
    return fields


def _xml_value(value):
    """An override value as a Properties value (sequences -> comma-separated string)."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    return ", ".join(_fmt(x) for x in np.asarray(value, np.float64).reshape(-1))


def _mitsuba_message(e: Exception) -> str:
    """Mitsuba's error without the Python traceback it embeds for plugin errors."""
    from mi_grg.data.inputs import without_traceback
    return " ".join(without_traceback(str(e)).split())


def load_scan(path, overrides: dict | None = None) -> Scan:
    """Read a scene file into a :class:`Scan`.

    ``overrides`` maps scanner field names (see ``SCANNER_FIELDS``) to values, e.g.
    ``{"views": 10}`` from a CLI flag. An override replaces the field and the fields that
    would contradict it (``views`` replaces ``angles``, ``test_views`` replaces
    ``test_angles``, ``noise="none"`` drops ``NOISE_FIELDS``). A value of ``None``
    removes the field (its default applies). Unknown names raise ``ScanError``.

    The file is read with Mitsuba's parser and then instantiated, so every plugin checks
    its own parameters (misspelled or unused ones are errors) exactly as ``mi.load_file``
    would; the geometry comes from the instantiated ``ct_scanner``.
    """
    return load_scan_and_scene(path, overrides)[0]


def load_scan_and_scene(path, overrides: dict | None = None) -> tuple:
    """``(load_scan(path, overrides), the Mitsuba scene it instantiated)``: for callers
    that render the file, so that its objects are built once."""
    import mitsuba as mi
    from mi_grg.variant import set_variant
    set_variant(mi.variant())  # our plugins, registered for the active variant
    path = Path(path)
    if not path.is_file():
        raise ScanError(f"scene file {path} does not exist")
    from mi_grg.data.inputs import InputError, check_xml
    try:
        check_xml(path, "scene file")     # bounded before Mitsuba's parser reads it
    except InputError as e:
        raise ScanError(str(e)) from None
    config = mi.parser.ParserConfig(mi.variant())
    try:
        state = mi.parser.parse_file(config, str(path))
    except RuntimeError as e:
        raise ScanError(f"{path}: {_mitsuba_message(e)}") from None
    top = [i for _, i in _children(state, 0)]
    sensors = [i for i in top if state.nodes[i].type == mi.ObjectType.Sensor]
    integrators = [i for i in top if state.nodes[i].type == mi.ObjectType.Integrator]
    names = [state.nodes[i].props.plugin_name() for i in sensors]
    if names != ["ct_scanner"]:
        raise ScanError(f"{path}: a scan scene has exactly one sensor, of type ct_scanner "
                        f"(found {names or 'none'})")
    if len(integrators) > 1:
        raise ScanError(f"{path}: more than one integrator")
    media = [i for _, i in _children(state, sensors[0])
             if state.nodes[i].type == mi.ObjectType.Medium]
    if overrides:
        props = state.nodes[sensors[0]].props
        children = dict(_children(state, sensors[0]))
        fields = {k: props[k] for k in props.keys() if k not in children}
        new = apply_overrides(fields, overrides)
        for k in fields:
            del props[k]
        for k, v in new.items():
            props[k] = _xml_value(v)
    # plain dicts first: the transformations below may rewrite the node list
    scan = Scan(geometry=None, path=str(path),
                object=_node_dict(state, media[0]) if media else {},
                integrator=_node_dict(state, integrators[0]) if integrators else {},
                other=[_node_dict(state, i) for i in top
                       if i not in sensors and i not in integrators])
    # Relative file names inside the scene resolve against its folder, as in mi.load_file.
    resolver = mi.file_resolver()
    saved = [str(resolver[i]) for i in range(len(resolver))]
    resolver.prepend(str(Path(path).resolve().parent))
    try:
        mi.parser.transform_all(config, state)
        scene = mi.parser.instantiate(config, state)
    except RuntimeError as e:
        raise ScanError(f"{path}: {_mitsuba_message(e)}") from None
    finally:
        resolver.clear()
        for p in saved:
            resolver.append(p)
    sensor = scene.sensors()[0]
    scan.geometry, scan.test_angles, scan.noise = (sensor.geometry, sensor.test_angles,
                                                   sensor.noise)
    return scan, scene


def load_mitsuba_scene(path, **params):
    """``mi.load_file`` after registering mi_grg's plugins for the active variant.

    ``params`` fill ``$name`` defaults of the file, as in ``mi.load_file``."""
    import mitsuba as mi
    from mi_grg.variant import set_variant
    set_variant(mi.variant())
    return mi.load_file(str(path), **params)


# ---------------------------------------------------------------- writing
def _fmt(x: float) -> str:
    return repr(float(x))  # shortest string that reads back to the same float64


def _vec(values) -> str:
    return " ".join(_fmt(x) for x in values)


def _prop(name, value, indent) -> str:
    if isinstance(value, dict):
        return _element(value, indent, name=name)
    if hasattr(value, "matrix"):   # a Mitsuba transform (e.g. a gridvolume's to_world)
        m = np.asarray(value.matrix, np.float64).reshape(-1)
        pad = " " * indent
        return (f"{pad}<transform name={quoteattr(name)}>\n{pad}    <matrix "
                f"value={quoteattr(_vec(m))}/>\n{pad}</transform>\n")
    if isinstance(value, bool):
        tag, text = "boolean", "true" if value else "false"
    elif isinstance(value, (int, np.integer)):
        tag, text = "integer", str(int(value))
    elif isinstance(value, (float, np.floating)):
        tag, text = "float", _fmt(value)
    elif isinstance(value, str):
        tag, text = "string", value
    else:
        raise ScanError(f"cannot write property {name}={value!r} to XML (only booleans, "
                        "integers, floats, strings, transforms and nested objects)")
    return f"{' ' * indent}<{tag} name={quoteattr(name)} value={quoteattr(text)}/>\n"


def tag_of(plugin: str, default=None) -> str:
    """The XML tag of a plugin type (medium, shape, ...)."""
    import mitsuba as mi
    tag = _tag_name(mi.PluginManager.instance().plugin_type(plugin)) or _TAGS.get(plugin)
    tag = tag or default
    if tag is None:
        raise ScanError(f"unknown Mitsuba plugin type {plugin!r}")
    return tag


def _element(d, indent, name=None, tag=None) -> str:
    d = dict(d)
    plugin = d.pop("type")
    tag = tag_of(plugin, tag)
    pad = " " * indent
    attrs = f" type={quoteattr(plugin)}"
    if name is not None and not name.startswith("_arg_"):
        attrs += f" name={quoteattr(name)}"
    if not d:
        return f"{pad}<{tag}{attrs}/>\n"
    body = "".join(_prop(k, v, indent + 4) for k, v in d.items())
    return f"{pad}<{tag}{attrs}>\n{body}{pad}</{tag}>\n"


def scanner_fields(scan: Scan) -> dict:
    """The ``ct_scanner`` fields (XML strings/numbers) that reproduce ``scan`` exactly.

    Angles equal to a full-circle ``views`` grid are written as ``views``; anything else
    as explicit radians (``repr`` precision, so reading them back is exact)."""
    g = scan.geometry
    f = {"mode": g.mode, "DSD": g.DSD, "DSO": g.DSO,
         "nDetector": " ".join(map(str, g.nDetector)), "sDetector": _vec(g.sDetector),
         "nVoxel": " ".join(map(str, g.nVoxel)), "sVoxel": _vec(g.sVoxel)}
    if any(g.offOrigin):
        f["offOrigin"] = _vec(g.offOrigin)
    if any(g.offDetector):
        f["offDetector"] = _vec(g.offDetector)
    n = g.n_views
    if np.array_equal(g.angles, circular_angles(n)):
        f["views"] = n
    else:
        f["angles"] = ", ".join(_fmt(a) for a in g.angles)
    t = np.asarray(scan.test_angles, np.float64).reshape(-1)
    if t.size:
        if np.array_equal(t, circular_angles(t.size) + 2 * np.pi / (2 * t.size)):
            f["test_views"] = int(t.size)
        else:
            f["test_angles"] = ", ".join(_fmt(a) for a in t)
    if g.per_view:
        f["vectors"] = "; ".join(" ".join(_fmt(x) for x in r) for r in g.view_vectors())
        if t.size:
            f["test_vectors"] = "; ".join(" ".join(_fmt(x) for x in r)
                                          for r in g.view_vectors(t))
    if scan.noise:
        f["noise"] = scan.noise["model"]
        f["I0"] = float(scan.noise["I0"])
        f["electronic_std"] = float(scan.noise["electronic_std"])
        # written always (Scan fills the defaults): scene.xml states every effect that ran
        f["noise_seed"] = int(scan.noise["seed"])
        f["clip_negative"] = bool(scan.noise["clip_negative"])
    return f


def scan_to_xml(scan: Scan) -> str:
    """The scene XML text of ``scan`` (see ``write_scan_xml``)."""
    body = "".join(_prop(k, v, 8) for k, v in scanner_fields(scan).items())
    if scan.object:
        body += _element(scan.object, 8, tag="medium")
    out = ['<?xml version="1.0" encoding="utf-8"?>\n',
           '<!-- CT scan written by mi_grg.data.scene.write_scan_xml; schema: docs/conventions.md -->\n',
           '<scene version="3.0.0">\n',
           f'    <sensor type="ct_scanner">\n{body}    </sensor>\n']
    if scan.integrator:
        out.append(_element(scan.integrator, 4, tag="integrator"))
    out += [_element(o, 4) for o in scan.other]
    out.append("</scene>\n")
    return "".join(out)


def write_scan_xml(scan: Scan, path) -> Path:
    """Write ``scan`` as a scene file; ``load_scan`` of it reproduces the geometry, test
    angles, noise, object, integrator and other objects exactly. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(scan_to_xml(scan))
    return path
