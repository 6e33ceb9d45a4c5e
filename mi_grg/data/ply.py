"""Radiative Gaussians as a 3DGS-style PLY, for inspection in existing splat viewers.

File layout (what 3D Gaussian Splatting's ``save_ply`` writes and its viewers read):
binary little-endian, one ``vertex`` element, float32 properties in this order

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  [f_rest_0 .. f_rest_44]  opacity
    scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

Mapping of a radiative Gaussian (position p, scales s, rotation q = (w, x, y, z),
density rho in 1/length) onto those fields:

* ``x y z`` = p; ``nx ny nz`` = 0 (unused by viewers).
* ``scale_k`` = log(s_k): viewers apply exp().
* ``rot_0..3`` = (w, x, y, z): viewers normalise the quaternion; ``load_ply`` does too.
* ``opacity`` = log(rho): viewers apply the sigmoid, so a splat's opacity is
  sigmoid(log rho) = rho / (1 + rho), monotone in the density, ~rho for thin media.
  ``load_ply`` inverts it exactly: rho = exp(opacity). Densities below exp(-60)
  (including 0) are written as -60 (opacity 9e-27) and read back as 0.
* ``f_dc_0..2`` = (g - 0.5) / C0 with C0 = 0.28209479 (the degree-0 SH constant) and
  g = rho / max(rho): viewers show the colour 0.5 + C0 f_dc = g, a grey level
  proportional to the density (the brightest Gaussian is white). Read back, it is ignored.
* ``f_rest_*`` (only with ``sh_rest=True``, for viewers that insist on degree-3 SH): 0.

Round trip: positions are exact; rotations are renormalised (<= 1 ulp of float32);
scales and densities pass through log/exp in float64 and agree to a relative 1e-6 (the
float32 rounding of the stored logarithm).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_grg.core.gaussians import Gaussians

SH_C0 = 0.28209479177387814         # Y_0^0 = 1 / (2 sqrt(pi)), as in 3DGS
OPACITY_FLOOR = -60.0               # log-density written for rho < exp(-60) (incl. 0)
N_SH_REST = 45                      # degree-3 SH: 15 coefficients x 3 colours

_NAMES = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"], ["opacity",
          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}
_REQUIRED = ("x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")


class PlyError(ValueError):
    """An unreadable or incomplete PLY file; the message names the problem."""


def property_names(sh_rest: bool = False) -> list:
    """The vertex properties in file order."""
    rest = [f"f_rest_{i}" for i in range(N_SH_REST)] if sh_rest else []
    return _NAMES[0] + rest + _NAMES[1]


def save_ply(gaussians: Gaussians, path, sh_rest: bool = False) -> Path:
    """Write ``gaussians`` as a binary little-endian 3DGS-style PLY (mapping: module doc).

    ``sh_rest`` adds 45 zero ``f_rest_*`` properties (degree-3 SH) for viewers that
    require them. Returns the path."""
    if not isinstance(gaussians, Gaussians):
        raise TypeError(f"gaussians must be mi_grg.core.gaussians.Gaussians, got "
                        f"{type(gaussians).__name__}")
    g = gaussians.numpy()
    pos = g["positions"].astype(np.float64)
    scales = g["scales"].astype(np.float64)
    q = g["rotations"].astype(np.float64)
    rho = g["densities"].astype(np.float64)
    for name, arr in (("positions", pos), ("scales", scales), ("rotations", q),
                      ("densities", rho)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or Inf")
    if np.any(scales <= 0):
        raise ValueError("scales must be > 0 (standard deviations, length)")
    if np.any(rho < 0):
        raise ValueError("densities must be >= 0 (1/length)")
    n = rho.size
    names = property_names(sh_rest)
    data = np.zeros(n, dtype=np.dtype([(k, "<f4") for k in names]))
    for k, axis in enumerate("xyz"):
        data[axis] = pos[:, k]
        data[f"scale_{k}"] = np.log(scales[:, k])
    for k in range(4):
        data[f"rot_{k}"] = q[:, k]
    with np.errstate(divide="ignore"):
        log_rho = np.log(rho)
    data["opacity"] = np.where(log_rho > OPACITY_FLOOR, log_rho, OPACITY_FLOOR)
    peak = rho.max() if n else 0.0
    grey = rho / peak if peak > 0 else np.zeros(n)
    for k in range(3):
        data[f"f_dc_{k}"] = (grey - 0.5) / SH_C0
    header = ["ply", "format binary_little_endian 1.0",
              "comment mi_grg radiative Gaussians: opacity = log(density), "
              "scale = log(std), rot = (w, x, y, z)",
              f"element vertex {n}"]
    header += [f"property float {k}" for k in names] + ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return path


def _read_header(f, path):
    first = f.readline()
    if first.strip() != b"ply":
        raise PlyError(f"{path}: not a PLY file (first line {first[:20]!r})")
    fmt, elements = None, []
    while True:
        line = f.readline()
        if not line:
            raise PlyError(f"{path}: header has no end_header")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"{path}: property before any element")
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            else:
                if words[1] not in _PLY_TYPES:
                    raise PlyError(f"{path}: unknown property type {words[1]!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    return fmt, elements


def load_ply(path) -> Gaussians:
    """Read a 3DGS-style PLY (``save_ply``'s or 3DGS's own) into ``Gaussians``.

    Uses x y z, scale_0..2 (log std), rot_0..3 (w, x, y, z; normalised here) and opacity
    (density = exp(opacity), see the module doc); other properties are ignored. Binary
    little- or big-endian files whose first element is ``vertex``."""
    path = Path(path)
    with open(path, "rb") as f:
        fmt, elements = _read_header(f, path)
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise PlyError(f"{path}: format {fmt!r} is not supported (binary PLY only)")
        if not elements or elements[0][0] != "vertex":
            raise PlyError(f"{path}: the first element must be 'vertex'")
        _, n, props = elements[0]
        if any(t is None for _, t in props):
            raise PlyError(f"{path}: list properties in 'vertex' are not supported")
        missing = [k for k in _REQUIRED if k not in [p for p, _ in props]]
        if missing:
            raise PlyError(f"{path}: vertex lacks properties {missing}")
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + t) for name, t in props])
        raw = f.read(dtype.itemsize * n)
        if len(raw) != dtype.itemsize * n:
            raise PlyError(f"{path}: expected {n} vertices ({dtype.itemsize * n} bytes), "
                           f"file has {len(raw)} bytes of data")
    data = np.frombuffer(raw, dtype=dtype, count=n)
    col = lambda k: np.asarray(data[k], np.float64)  # noqa: E731
    pos = np.stack([col(k) for k in "xyz"], -1)
    scales = np.exp(np.stack([col(f"scale_{k}") for k in range(3)], -1))
    q = np.stack([col(f"rot_{k}") for k in range(4)], -1)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(norm == 0) or not np.all(np.isfinite(q)):
        raise PlyError(f"{path}: rot_0..3 holds a zero or non-finite quaternion")
    opacity = col("opacity")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(opacity))
            and np.all(opacity < 88.0)):   # exp(88) overflows float32
        raise PlyError(f"{path}: non-finite positions or opacities (or opacity >= 88)")
    rho = np.where(opacity <= OPACITY_FLOOR, 0.0, np.exp(opacity))
    return Gaussians.from_numpy(pos, scales, q / norm, rho)
