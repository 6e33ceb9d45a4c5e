"""NAF / SAX-NeRF pickles: loaded safely, read as R2-Gaussian's ``readNAFInfo`` reads them.

Pickles can run code when loaded; ``load_naf`` accepts only dicts, lists, tuples, numbers,
strings and numpy arrays of numbers (``_RestrictedUnpickler``: an explicit allow-list of
numpy's reconstructors, protocols 2 to 5) and refuses anything else.
"""
from __future__ import annotations

import pickle
import warnings
from pathlib import Path

import numpy as np

from mi_grg.core.geometry import Geometry, GeometryError
from mi_grg.data.case import Case
from mi_grg.data.dataset import DatasetError


def _latin1_bytes(text, encoding="utf-8"):
    """Protocol 2 writes each bytes object as ``_codecs.encode(text, "latin1")``; only that
    call is accepted (another codec could be anything)."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"refuses _codecs.encode({type(text).__name__}, "
                                     f"{encoding!r}); only latin1 text (protocol 2 bytes)")
    return text.encode("latin1")


#: What numpy's pickles call, in numpy 1 (``numpy.core``) and numpy 2 (``numpy._core``)
#: spelling: array and scalar reconstructors (protocols 2 to 4) and ``_frombuffer``
#: (protocol 5). None of them runs code of the pickle's choosing.
_NUMPY_RECONSTRUCTORS = {(f"{pkg}.{module}", name) for pkg in ("numpy.core", "numpy._core")
                         for module, name in (("multiarray", "_reconstruct"),
                                              ("multiarray", "scalar"),
                                              ("numeric", "_frombuffer"))}


class _RestrictedUnpickler(pickle.Unpickler):
    """Accepts only what a NAF pickle holds: dicts, lists, tuples, numbers, strings,
    None and numpy arrays / scalars, written with any protocol from 2 to 5. Any other
    callable or class (which could run code) is refused before it is called."""

    ALLOWED = _NUMPY_RECONSTRUCTORS | {("numpy", "ndarray"), ("numpy", "dtype"),
                                       ("builtins", "complex"), ("__builtin__", "complex")}
    GUARDED = {("_codecs", "encode"): _latin1_bytes}

    def find_class(self, module, name):
        if (module, name) in self.GUARDED:
            return self.GUARDED[module, name]
        if (module, name) in self.ALLOWED:
            with warnings.catch_warnings():   # numpy 2 warns on the numpy.core spelling
                warnings.simplefilter("ignore", DeprecationWarning)
                return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refuses the type {module}.{name}")


def _plain(obj, where):
    """Check that ``obj`` holds only the allowed types (numpy object arrays are not)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                raise DatasetError(f"{where}: key {k!r} is not a string")
            _plain(v, f"{where}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _plain(v, f"{where}[{i}]")
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise DatasetError(f"{where}: array of dtype {obj.dtype}; expected numbers")
    elif not (obj is None or isinstance(obj, (bool, int, float, str, np.generic))):
        raise DatasetError(f"{where}: unexpected type {type(obj).__name__}")


def load_naf(path) -> dict:
    """A NAF / SAX-NeRF pickle, loaded with ``_RestrictedUnpickler`` and type-checked."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = _RestrictedUnpickler(f).load()
    except pickle.UnpicklingError as e:
        if "refuses" not in str(e):   # not a refusal: a damaged file
            raise DatasetError(f"{path}: cannot read as a pickle ({e}); expected a complete "
                               "NAF pickle") from e
        raise DatasetError(f"{path}: {e} (only dicts, lists, numbers, strings and numpy "
                             "arrays are accepted)") from e
    except Exception as e:
        raise DatasetError(f"{path}: cannot read as a pickle ({type(e).__name__}: {e})") \
            from e
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a dict at the top, got {type(data).__name__}")
    try:
        _plain(data, path.name)
    except RecursionError:
        raise DatasetError(f"{path}: nested too deeply to be a NAF pickle") from None
    return data


#: NAF pickles state lengths in mm but their projections were computed in metres (NAF's
#: generator divides by 1000 before calling TIGRE); R2-Gaussian's reader (readNAFInfo)
#: divides the lengths by 1000 too, and so do we: lengths in m, densities in 1/m.
NAF_LENGTH_SCALE = 1e-3


def naf_case(data: dict, path) -> tuple:
    """(Case, notes) from a loaded NAF pickle, read as R2-Gaussian's ``readNAFInfo`` reads
    it: fields in its layout's order (nDetector [v, u], projections [view, v, u] line
    integrals, angles in radians, image [x, y, z]), lengths x ``NAF_LENGTH_SCALE`` (m);
    "val" becomes the test split."""
    name = Path(path).name

    def field(key, where=data, label=None):
        label = label or key
        if key not in where:
            raise DatasetError(f"{name}: lacks the field {label}")
        return where[key]

    def vec(key, n):
        try:
            v = np.asarray(field(key), np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DatasetError(f"{name}: {key} must be {n} numbers") from None
        if v.size != n:
            raise DatasetError(f"{name}: {key} must have {n} entries, got {v.size}")
        return v

    nDet, dDet = vec("nDetector", 2), vec("dDetector", 2)
    nVox, dVox = vec("nVoxel", 3), vec("dVoxel", 3)
    splits = {}
    for split in ("train", "val"):
        block = field(split)
        if not isinstance(block, dict):
            raise DatasetError(f"{name}: {split} must be a dict with projections and angles")
        proj = field("projections", block, f"{split}.projections")
        ang = field("angles", block, f"{split}.angles")
        if not isinstance(proj, np.ndarray) or proj.ndim != 3:
            raise DatasetError(f"{name}: {split}.projections must be an array "
                                 "[view, v, u]")
        ang = np.asarray(ang, np.float64).reshape(-1)
        if ang.size != proj.shape[0]:
            raise DatasetError(f"{name}: {split}.angles has {ang.size} entries for "
                                 f"{proj.shape[0]} projections")
        if proj.shape[1:] != tuple(int(x) for x in nDet):
            raise DatasetError(f"{name}: {split}.projections has [v, u] = "
                                 f"{list(proj.shape[1:])}, nDetector says {nDet.tolist()}")
        if not (np.all(np.isfinite(proj)) and np.all(np.isfinite(ang))):
            raise DatasetError(f"{name}: {split} holds NaN/Inf")
        splits[split] = (proj.astype(np.float32), ang)
    try:
        geo = Geometry(mode=str(field("mode")), DSD=field("DSD"), DSO=field("DSO"),
                       nDetector=nDet, sDetector=nDet * dDet, nVoxel=nVox, sVoxel=nVox * dVox,
                       offOrigin=data.get("offOrigin", (0, 0, 0)),
                       offDetector=data.get("offDetector", (0, 0)),
                       angles=splits["train"][1]).scaled(NAF_LENGTH_SCALE)
    except DatasetError:
        raise
    except (GeometryError, TypeError, ValueError) as e:
        raise DatasetError(f"{name}: {e}") from e
    vol = data.get("image")
    if vol is not None:
        vol = np.asarray(vol, np.float32)
        if vol.shape != geo.nVoxel:
            raise DatasetError(f"{name}: image has shape {list(vol.shape)}, nVoxel says "
                                 f"[x, y, z] = {list(geo.nVoxel)}")
    extras = {k: data[k] for k in ("accuracy", "totalAngle", "startAngle", "numTrain",
                                   "numVal", "filter") if k in data}
    case = Case(geometry=geo, train=splits["train"][0], test_angles=splits["val"][1],
                test=splits["val"][0], vol_gt=vol)
    return case, {"pickle_extras": extras,
                  "unknown_keys": sorted(set(data) - {
                      "DSD", "DSO", "nVoxel", "dVoxel", "nDetector", "dDetector", "offOrigin",
                      "offDetector", "totalAngle", "startAngle", "accuracy", "mode",
                      "numTrain", "numVal", "train", "val", "image", "filter"})}
