"""A checkpoint file read whole and checked before a run resumes from it.

``read_checkpoint`` reads every array of the ``.npz`` (a truncated or damaged file fails
here, naming it) and checks each parameter block (``raw__*``, ``kept__*``): every array
present, [N, width] with one N, finite; Adam's moments and the densification statistics
have raw's N rows. ``checked_meta`` checks the meta record's fields and their types. Any
fault is a ValueError naming the file and the array or field, never a failure deep inside
the optimiser.
"""
from __future__ import annotations

import json

import numpy as np

#: Width of each parameter array ([N] for 1).
WIDTHS = {"positions": 3, "raw_scales": 3, "raw_rotations": 4, "raw_densities": 1}
#: Fields of the meta record and their JSON types.
META_TYPES = {"iteration": int, "rng": dict, "log": list, "seconds": (int, float),
              "config": dict, "adam_steps": dict, "stopper": (dict, type(None)),
              "stopped_by": (str, type(None))}


class Arrays(dict):
    """A checkpoint's arrays, read as ``np.load``'s archive is (``.files``, a context)."""

    @property
    def files(self) -> list:
        return list(self)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def read_checkpoint(path, groups) -> Arrays:
    """Every array of the checkpoint at ``path``, checked (see the module docstring);
    ``groups``: the parameter names."""
    import zipfile
    import zlib
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise ValueError(f"cannot read checkpoint {path}: {e or type(e).__name__} "
                         "(truncated?)") from None
    if "meta" not in arrays:
        raise ValueError(f"{path} is not a training checkpoint (no meta record)")
    n = _check_block(arrays, "raw", groups, path)
    kept = (_check_block(arrays, "kept", groups, path)
            if any(f"kept__{k}" in arrays for k in groups) else None)
    gp, ks = arrays.get("graph_positions"), arrays.get("kept_density_scale")
    if gp is not None and (gp.ndim != 2 or gp.shape[1] != 3):
        raise ValueError(f"checkpoint {path}: graph_positions has shape {list(gp.shape)}, "
                         "expected [M, 3]")
    if ks is not None and (kept is None or ks.shape != (kept,)):
        raise ValueError(f"checkpoint {path}: kept_density_scale has shape {list(ks.shape)}, "
                         f"expected the kept state's [{kept}]")
    for key, a in arrays.items():
        if key.startswith(("adam_", "dens_")) and (a.ndim == 0 or a.shape[0] != n):
            raise ValueError(f"checkpoint {path}: {key} has shape {list(a.shape)}, expected "
                             f"{n} rows (one per Gaussian)")
        if key != "meta" and not (np.issubdtype(a.dtype, np.floating)
                                  and np.all(np.isfinite(a))):
            raise ValueError(f"checkpoint {path}: {key} is not finite floats ({a.dtype})")
    return Arrays(arrays)


def _check_block(arrays: dict, prefix: str, groups, path) -> int:
    """N of the parameter block ``prefix`` (every array there, [N, width], finite)."""
    rows = None
    for key in groups:
        name, width = f"{prefix}__{key}", WIDTHS.get(key, 1)
        a = arrays.get(name)
        if a is None:
            raise ValueError(f"checkpoint {path}: lacks the array {name}")
        rows = a.shape[0] if rows is None and a.ndim else rows
        shapes = [(rows,), (rows, 1)] if width == 1 else [(rows, width)]
        if a.shape not in shapes:
            raise ValueError(f"checkpoint {path}: {name} has shape {list(a.shape)}, expected "
                             f"{list(shapes[-1])}")
        if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)):
            raise ValueError(f"checkpoint {path}: {name} is not finite floats ({a.dtype}"
                             f"{', NaN or Inf' if a.dtype.kind == 'f' else ''})")
    return rows


def checked_meta(f, path, groups) -> dict:
    """The meta record of checkpoint ``f`` (from ``read_checkpoint``), its fields checked."""
    try:
        meta = json.loads(bytes(f["meta"]).decode())
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise ValueError(f"checkpoint {path}: its meta record is not JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"checkpoint {path}: its meta record is not an object")
    for key, kind in META_TYPES.items():
        value = meta.get(key)
        if key not in meta or not isinstance(value, kind) or isinstance(value, bool):
            raise ValueError(f"checkpoint {path}: its meta record lacks {key!r} or has the "
                             f"wrong type ({type(value).__name__})")
    bad = [n for n, v in meta["adam_steps"].items()
           if n not in groups or not isinstance(v, int) or isinstance(v, bool)
           or f"adam_m__{n}" not in f.files or f"adam_v__{n}" not in f.files]
    if bad:
        raise ValueError(f"checkpoint {path}: adam_steps names group(s) {bad} without their "
                         "moments")
    return meta
