"""Read and write R2-Gaussian's data layout (its published data sets load unchanged).

Layout of a case directory ``DIR`` (R2-Gaussian's ``readBlenderInfo`` / ``generate_data.py``)::

    DIR/meta_data.json   {"scanner": {mode, DSD, DSO, nDetector [v, u], sDetector [v, u],
                                      dDetector, nVoxel [x, y, z], sVoxel, dVoxel, offOrigin,
                                      offDetector, + TIGRE extras (accuracy, filter,
                                      totalAngle, startAngle, noise settings, ...)},
                          "vol": "vol_gt.npy",                    # optional here
                          "bbox": [[xmin, ymin, zmin], [xmax, ymax, zmax]],
                          "proj_train": [{"file_path": "proj_train/proj_train_0000.npy",
                                          "angle": <radians>,
                                          "vector": [12 numbers]}, ...],  # optional
                          "proj_test": [...],
                          "mi_grg": {...}}                        # our Case.info; R2 ignores it
    DIR/proj_*/...npy    float32 [v, u] line integrals (or .exr, single channel "Y")
    DIR/vol_gt.npy       float32 density [x, y, z]
    DIR/scene.xml        the simulated scan as scene XML (``mi-grg simulate`` writes it;
                         not part of R2's layout, and load_case does not read it)

Units: files hold the data set's own units. ``load_case(rescale=True)`` multiplies every
length AND every projection by ``scene_scale = 2 / max(sVoxel)`` (R2-Gaussian does the same
so that the volume fills [-1, 1]^3; line integrals scale with length because densities are
left unchanged). ``save_case`` undoes that, so load -> save reproduces the files.

Per-view scans: every entry (train and test) may carry "vector", the view's 12 numbers in
ASTRA's cone_vec order (source, detector centre, column step u, row step v; parallel3d_vec
for parallel beam; ``mi_grg.core.view_vectors``) beside its nominal "angle"; all entries
or none.
"""
from __future__ import annotations

import json
import math
import numbers
import warnings
from pathlib import Path

import numpy as np

from mi_grg.data.case import Case
from mi_grg.core.geometry import Geometry, GeometryError

META_NAME = "meta_data.json"
VOL_NAME = "vol_gt.npy"
OUR_KEY = "mi_grg"

#: Negative line integrals down to ``-NEG_TOL_REL * max`` (max of the split's projections)
#: are noise (e.g. R2-style Poisson/Gaussian noise on near-empty rays) and are clamped to 0
#: with a warning; anything more negative is an error (wrong sign, not -log(I/I0), ...).
NEG_TOL_REL = 1e-2

#: TIGRE keys written into the scanner block when ``case.info`` does not give them:
#: R2-Gaussian's ``get_geometry`` (FDK initialisation) reads both.
TIGRE_DEFAULTS = {"accuracy": 0.5, "filter": None}

_GEOMETRY_KEYS = ("mode", "DSD", "DSO", "nDetector", "sDetector", "dDetector", "nVoxel",
                  "sVoxel", "dVoxel", "offOrigin", "offDetector")


class DatasetError(ValueError):
    """Invalid data on disk or in a Case; the message names the file or field."""


class DatasetWarning(UserWarning):
    """Data was repaired on load (e.g. small negative line integrals clamped to 0)."""


# ---------------------------------------------------------------- OpenEXR
def write_exr(path, image) -> Path:
    """Write a 2-D image [v, u] as a single-channel ("Y") float32 OpenEXR file (ZIP)."""
    import OpenEXR
    arr = np.asarray(image)
    if arr.ndim != 2 or arr.size == 0:
        raise DatasetError(f"{path}: an EXR image must be 2-D [v, u], got shape {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = Path(path)
    OpenEXR.File(header, {"Y": arr}).write(str(path))
    return path


def read_exr(path) -> np.ndarray:
    """Read a single-channel OpenEXR image -> float32 [v, u] (channel "Y", or the only one)."""
    import OpenEXR
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: EXR file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = f.channels()
            if "Y" in channels:
                pixels = channels["Y"].pixels
            elif len(channels) == 1:
                pixels = next(iter(channels.values())).pixels
            else:
                raise DatasetError(f"{path}: expected one channel 'Y', found {sorted(channels)}")
            pixels = np.array(pixels, dtype=np.float32)   # copy: the File owns its buffer
    except DatasetError:
        raise
    except Exception as e:  # OpenEXR raises RuntimeError/ValueError on corrupt files
        raise DatasetError(f"{path}: cannot read as OpenEXR ({e})") from e
    if pixels.ndim != 2:
        raise DatasetError(f"{path}: expected a 2-D image [v, u], got shape {pixels.shape}")
    return pixels


# ---------------------------------------------------------------- helpers
def json_default(obj):
    """JSON for what NumPy and pathlib hand over: scalars, arrays (as lists), paths."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _load_image(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{what}: file {path} not found")
    if path.suffix.lower() == ".exr":
        return read_exr(path)
    if path.suffix.lower() != ".npy":
        raise DatasetError(f"{what}: {path} must be .npy or .exr")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise DatasetError(f"{what}: cannot read {path} as .npy ({e})") from e
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise DatasetError(f"{what}: {path} must hold real numbers, got dtype {arr.dtype}")
    return arr


def _angle(entry, where: str) -> float:
    if not isinstance(entry, dict):
        raise DatasetError(f"{where} must be an object with file_path and angle, got {entry!r}")
    for key in ("file_path", "angle"):
        if key not in entry:
            raise DatasetError(f"{where} lacks '{key}'")
    a = entry["angle"]
    if isinstance(a, bool) or not isinstance(a, numbers.Real) or not math.isfinite(a):
        raise DatasetError(f"{where}.angle must be a finite number (radians), got {a!r}")
    if not isinstance(entry["file_path"], str) or not entry["file_path"]:
        raise DatasetError(f"{where}.file_path must be a non-empty path, got "
                           f"{entry['file_path']!r}")
    return float(a)


def _check_stack(stack: np.ndarray, split: str):
    """Finite and (up to noise) non-negative; small negatives are clamped (see NEG_TOL_REL).

    Returns (stack, clamp record): the record is ``{}`` or ``{"count", "min", "tolerance"}``
    (file units), so that the repair is echoed into metrics.json, not only warned about."""
    if not np.all(np.isfinite(stack)):
        bad = np.argwhere(~np.isfinite(stack))[0]
        raise DatasetError(f"{split}: projections contain NaN/Inf (first at [view, v, u] = "
                           f"{bad.tolist()})")
    neg = stack < 0
    n_neg = int(np.count_nonzero(neg))
    if n_neg:
        peak = float(stack.max())
        tol = NEG_TOL_REL * max(peak, 0.0)
        low = float(stack.min())
        if low < -tol:
            where = np.unravel_index(int(np.argmin(stack)), stack.shape)
            raise DatasetError(
                f"{split}: line integral {low:.4g} at [view, v, u] = {list(map(int, where))} "
                f"is below -{NEG_TOL_REL} x max ({-tol:.4g}); projections must be "
                "non-negative line integrals -log(I/I0)")
        warnings.warn(f"{split}: clamped {n_neg} negative line integral(s) (min {low:.3g}, "
                      f"tolerance {tol:.3g} = {NEG_TOL_REL} x max) to 0", DatasetWarning,
                      stacklevel=3)
        stack = np.maximum(stack, 0, out=stack)
        return stack, {"count": n_neg, "min": low, "tolerance": tol}
    return stack, {}


def _read_split(root: Path, meta: dict, split: str, geo_shape, required: bool):
    """Angles [view], projections [view, v, u] float32 (file units) and the clamp record
    (see ``_check_stack``) of one split."""
    key = "proj_" + split
    entries = meta.get(key, [])
    if entries is None:
        entries = []
    if not isinstance(entries, list):
        raise DatasetError(f"{root / META_NAME}: '{key}' must be a list, got "
                           f"{type(entries).__name__}")
    if not entries:
        if required:
            raise DatasetError(f"{root / META_NAME}: '{key}' is empty or missing; at least one "
                               "training projection is needed")
        return np.zeros(0), None, {}
    angles = np.array([_angle(e, f"{key}[{i}]") for i, e in enumerate(entries)])
    stack = np.empty((len(entries), *geo_shape), np.float32)
    for i, e in enumerate(entries):
        path = _inside(root, e["file_path"], f"{key}[{i}].file_path")
        img = _load_image(path, f"{key}[{i}]")
        if img.dtype.kind in "biu":
            raise DatasetError(f"{key}[{i}]: {path} holds integers ({img.dtype}), not line "
                               "integrals -log(I/I0); import raw counts with `mi-grg import` "
                               "(docs/real_data.md)")
        if img.shape != tuple(geo_shape):
            raise DatasetError(f"{key}[{i}]: {path} has shape {list(img.shape)}, expected "
                               f"[v, u] = {list(geo_shape)} (scanner nDetector)")
        stack[i] = img
    stack, clamp = _check_stack(stack, key)
    return angles, stack, clamp


def _inside(root: Path, rel, what: str) -> Path:
    """``root / rel``, refused (naming ``what``) unless it lies inside the case folder: a
    data set reads only its own files."""
    if not isinstance(rel, str) or not rel:
        raise DatasetError(f"{root / META_NAME}: {what} must be a file name, got {rel!r}")
    path = root / rel
    if Path(rel).is_absolute() or root.resolve() not in path.resolve().parents:
        raise DatasetError(f"{root / META_NAME}: {what} {str(rel)[:200]!r} points outside the "
                           "case folder; a data set's files lie inside it")
    return path


def _check_memory(meta: dict, geo: Geometry, root: Path) -> None:
    """Refuse a case whose projections and ground truth would not fit, before they are
    read (``mi_grg.core.memory``)."""
    from mi_grg.core import memory
    n = sum(len(meta[k]) for k in ("proj_train", "proj_test") if isinstance(meta.get(k), list))
    needs = [memory.projections(n, geo.nDetector, copies=2)]
    if meta.get("vol"):
        needs.append(memory.volume(geo.nVoxel, copies=2, what="ground truth"))
    memory.check(needs, str(root / META_NAME), lower="a smaller case (nVoxel, nDetector)")


def _read_meta(meta_path: Path) -> tuple:
    """(meta_data.json's content, nDetector [v, u]), read within bounds, and the case's
    size checked against the memory there is before its arrays are read."""
    from mi_grg.data.inputs import InputError, read_json
    try:
        meta = read_json(meta_path, META_NAME)
    except InputError as e:
        raise DatasetError(str(e)) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("scanner"), dict):
        raise DatasetError(f"{meta_path}: lacks the 'scanner' object")
    try:
        probe = Geometry.from_scanner_dict(meta["scanner"], [0.0])
    except (GeometryError, TypeError, ValueError) as e:
        raise DatasetError(f"{meta_path}: scanner: {e}") from e
    _check_memory(meta, probe, meta_path.parent)
    return meta, probe.nDetector


def _entry_vectors(meta: dict):
    """(rows [m, 12] float64, entry names) of proj_train then proj_test entries carrying
    "vector", or None where none does; a mix is an error."""
    rows, names, plain = [], [], None
    for key in ("proj_train", "proj_test"):
        entries = meta.get(key) or []
        for i, e in enumerate(entries):
            name = f"{key}[{i}]"
            if isinstance(e, dict) and "vector" in e:
                rows.append(e["vector"])
                names.append(name)
            elif plain is None:
                plain = name
    if not rows:
        return None
    if plain is not None:
        raise DatasetError(f"{META_NAME}: {names[0]} has a \"vector\" but {plain} has none "
                           "(per-view vectors go on every entry or on none)")
    return rows, names


def _with_entry_vectors(geo: Geometry, meta: dict, test_angles) -> Geometry:
    """``geo`` with the entries' per-view vectors (train and test views), if any."""
    from mi_grg.core import view_vectors as vv
    found = _entry_vectors(meta)
    if found is None:
        return geo
    rows, names = found
    try:
        vec = vv.check_vectors(rows, geo.mode, geo.nDetector, geo.bbox(), names)
    except vv.VectorError as e:
        raise DatasetError(f"{META_NAME}: {e}") from None
    all_angles = np.concatenate([geo.angles, np.asarray(test_angles, np.float64)])
    return geo.replace(vectors=vec, vector_angles=all_angles)


# ---------------------------------------------------------------- load
def load_case(path, rescale: bool = True) -> Case:
    """Load a case directory in R2-Gaussian's layout (or the path of its meta_data.json).

    Args:
        path: the case directory.
        rescale: multiply all lengths (DSD, DSO, sDetector, dDetector, sVoxel, dVoxel,
            offOrigin, offDetector) and all projections by ``2 / max(sVoxel)`` as
            R2-Gaussian's reader does; ``case.scene_scale`` records the factor (1.0 without).
            Densities (vol_gt) are never rescaled.
    Returns:
        A Case: train [view, v, u] and test float32 line integrals, angles in radians,
        vol_gt [x, y, z] float32 or None (no "vol" key or no file), info = the "mi_grg"
        block when present; for foreign files, info["scanner_extras"] holds the scanner's
        non-geometry TIGRE keys so that ``save_case`` writes them back.
    Raises:
        DatasetError naming the file/field: missing files, shapes that disagree with
        nDetector / nVoxel, NaN/Inf, line integrals below ``-NEG_TOL_REL x max``, empty
        proj_train, non-numeric angles. Small negatives are clamped with a DatasetWarning
        and recorded in ``case.clamped`` (per split: count, min, tolerance; file units).
    """
    root = Path(path)
    if root.is_file() and root.name.endswith(".json"):
        root = root.parent
    meta_path = root / META_NAME
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path} not found (expected an R2-Gaussian case directory)")
    meta, nv_nu = _read_meta(meta_path)
    scanner = meta["scanner"]
    train_angles, train, train_clamp = _read_split(root, meta, "train", nv_nu, required=True)
    test_angles, test, test_clamp = _read_split(root, meta, "test", nv_nu, required=False)
    clamped = {k: v for k, v in (("proj_train", train_clamp), ("proj_test", test_clamp)) if v}
    try:
        geo = Geometry.from_scanner_dict(scanner, train_angles)
        geo = _with_entry_vectors(geo, meta, test_angles)
    except (GeometryError, TypeError, ValueError) as e:
        raise DatasetError(f"{meta_path}: {e}") from e

    vol = None
    vol_name = meta.get("vol")
    if vol_name:
        vol_path = _inside(root, vol_name, "vol")
        if vol_path.is_file():
            vol = _load_image(vol_path, "vol")
            if vol.shape != geo.nVoxel:
                raise DatasetError(f"vol: {vol_path} has shape {list(vol.shape)}, expected "
                                   f"[x, y, z] = {list(geo.nVoxel)} (scanner nVoxel)")
            vol = vol.astype(np.float32, copy=False)
            if not np.all(np.isfinite(vol)):
                raise DatasetError(f"vol: {vol_path} contains NaN/Inf "
                                   f"({np.count_nonzero(~np.isfinite(vol))} voxels)")
        else:
            warnings.warn(f"{meta_path}: vol file {vol_path} not found; vol_gt = None",
                          DatasetWarning, stacklevel=2)

    if OUR_KEY in meta:
        info = meta[OUR_KEY]
        if not isinstance(info, dict):
            raise DatasetError(f"{meta_path}: '{OUR_KEY}' must be an object")
        info = dict(info)
    else:
        extras = {k: v for k, v in scanner.items() if k not in _GEOMETRY_KEYS}
        info = {"scanner_extras": extras} if extras else {}

    scale = geo.scene_scale if rescale else 1.0
    if rescale:
        geo = geo.scaled(scale)
        train *= np.float32(scale)
        if test is not None:
            test *= np.float32(scale)
    return Case(geometry=geo, train=train, test_angles=test_angles, test=test, vol_gt=vol,
                scene_scale=float(scale), info=info, clamped=clamped)


# ---------------------------------------------------------------- save
def _validated_stack(arr, n_views, geo, name):
    a = np.asarray(arr)
    expected = (n_views, *geo.nDetector)
    if a.shape != expected:
        raise DatasetError(f"case.{name} has shape {list(a.shape)}, expected [view, v, u] = "
                           f"{list(expected)}")
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"case.{name} contains NaN/Inf")
    return a


def _vectors_of(geo: Geometry, angles):
    """The per-view rows of ``angles`` (None for a circular scan)."""
    if not geo.per_view or len(angles) == 0:
        return None
    try:
        return geo.view_vectors(angles)
    except GeometryError as e:
        raise DatasetError(f"case: {e}") from None


def save_case(case: Case, out_dir, exr: bool = False) -> Path:
    """Write ``case`` in R2-Gaussian's layout, in FILE units, and return ``out_dir``.
    A per-view scan writes each entry's "vector" (12 numbers, ``view_vectors`` order).

    Lengths and projections are divided by ``case.scene_scale`` (undoing ``load_case``'s
    rescale). ``case.info`` is stored under "mi_grg" in meta_data.json; its optional
    "scanner_extras" dict (TIGRE keys) is merged over ``TIGRE_DEFAULTS`` into the scanner
    block. With ``exr=True`` each projection is also written as a single-channel float32
    OpenEXR file next to its .npy (meta_data.json keeps pointing at the .npy files).
    """
    geo = case.geometry
    s = float(case.scene_scale)
    if not math.isfinite(s) or s <= 0:
        raise DatasetError(f"case.scene_scale must be finite and > 0, got {case.scene_scale!r}")
    test_angles = np.asarray(case.test_angles, np.float64).reshape(-1)
    if not np.all(np.isfinite(test_angles)):
        raise DatasetError("case.test_angles must be finite (radians)")
    train = _validated_stack(case.train, geo.n_views, geo, "train")
    test = None
    if case.test is not None or test_angles.size:
        if case.test is None:
            raise DatasetError(f"case.test is None but case.test_angles has "
                               f"{test_angles.size} entries")
        test = _validated_stack(case.test, test_angles.size, geo, "test")
    vol = None
    if case.vol_gt is not None:
        vol = np.asarray(case.vol_gt)
        if vol.shape != geo.nVoxel:
            raise DatasetError(f"case.vol_gt has shape {list(vol.shape)}, expected [x, y, z] = "
                               f"{list(geo.nVoxel)}")
        vol = vol.astype(np.float32)
        if not np.all(np.isfinite(vol)):
            raise DatasetError("case.vol_gt contains NaN/Inf")

    info = dict(case.info or {})
    extras = info.get("scanner_extras", {})
    if not isinstance(extras, dict):
        raise DatasetError("case.info['scanner_extras'] must be a dict of TIGRE keys")
    clash = sorted(set(extras) & set(_GEOMETRY_KEYS))
    if clash:
        raise DatasetError(f"case.info['scanner_extras'] must not override geometry keys {clash}")

    try:   # before writing anything
        json.dumps(info, default=json_default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"case.info must be JSON serialisable with finite numbers ({e})") \
            from e

    file_geo = geo if s == 1.0 else geo.scaled(1.0 / s)
    if s != 1.0:
        train = train / np.float32(s)
        test = None if test is None else test / np.float32(s)
    scanner = {**file_geo.to_scanner_dict(), **TIGRE_DEFAULTS, **extras}

    out = Path(out_dir)
    meta = {"scanner": scanner}
    if vol is not None:
        meta["vol"] = VOL_NAME
    meta["bbox"] = file_geo.bbox().tolist()   # file units (R2's reader does not read it)
    splits = (("proj_train", train, file_geo.angles), ("proj_test", test, test_angles))
    for key, stack, angles in splits:
        meta[key] = []
        if stack is None:
            continue
        (out / key).mkdir(parents=True, exist_ok=True)
        vec = _vectors_of(file_geo, angles)
        for i, (img, a) in enumerate(zip(stack, angles)):
            rel = f"{key}/{key}_{i:04d}.npy"
            np.save(out / rel, np.ascontiguousarray(img))
            if exr:
                write_exr((out / rel).with_suffix(".exr"), img)
            meta[key].append({"file_path": rel, "angle": float(a)})
            if vec is not None:
                meta[key][-1]["vector"] = [float(x) for x in vec[i]]
    meta[OUR_KEY] = info
    out.mkdir(parents=True, exist_ok=True)
    if vol is not None:
        np.save(out / VOL_NAME, vol)
    (out / META_NAME).write_text(json.dumps(meta, indent=4, default=json_default))
    return out
