"""Scan geometry files of other tools, read into a ``Geometry`` for ``mi-grg import``:

* an ASTRA vector file: one row of 12 numbers per view (``cone_vec``: source, detector
  centre, u step, v step; ``mi_grg.core.view_vectors``), whitespace or comma separated,
  ``#`` comments;
* an RTK geometry XML (``ThreeDCircularProjectionGeometry``, as RTK writes it): per view
  GantryAngle, OutOfPlaneAngle, InPlaneAngle (degrees), SourceOffsetX/Y,
  ProjectionOffsetX/Y, SourceToIsocenterDistance, SourceToDetectorDistance, each given
  once for all views or per view. RTK's fixed frame rotates about +Y; it maps onto
  mi_grg's by (X, Y, Z) = (y, -z, x) with gantry angle = view angle (the mapping of
  tests/test_voxel_projector.py); the projections' pixel grid is taken centred on the
  detector origin (RTK keeps the grid's origin in its image files, TIFFs do not);
* a Nikon XTEK ``.xtekct`` file (INI, section [XTekCT]): SrcToObject, SrcToDetector,
  DetectorPixelsX/Y, DetectorPixelSizeX/Y, DetectorOffsetX/Y, Projections, InitialAngle,
  AngularStep (degrees; a ``<Name>.ang`` or ``_ctdata.txt`` beside it gives the angles of
  each view), Name (projections ``<Name>_NNNN.tif``). Lengths in mm.

Every reader returns plain values; errors are one-line ``DatasetError``s naming the file
and the view or key.
"""
from __future__ import annotations

import configparser
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from mi_grg.core import view_vectors as vv
from mi_grg.data.dataset import DatasetError

__all__ = ["read_astra_vectors", "read_rtk_geometry", "read_xtekct", "nominal_fields"]

RTK_KEYS = ("GantryAngle", "OutOfPlaneAngle", "InPlaneAngle", "SourceOffsetX",
            "SourceOffsetY", "ProjectionOffsetX", "ProjectionOffsetY",
            "SourceToIsocenterDistance", "SourceToDetectorDistance")
RTK_DEFAULTS = {"OutOfPlaneAngle": 0.0, "InPlaneAngle": 0.0, "SourceOffsetX": 0.0,
                "SourceOffsetY": 0.0, "ProjectionOffsetX": 0.0, "ProjectionOffsetY": 0.0}
XTEK_REQUIRED = ("SrcToObject", "SrcToDetector", "DetectorPixelsX", "DetectorPixelsY",
                 "DetectorPixelSizeX", "DetectorPixelSizeY", "Projections")
#: Keys of a real scan's alignment that the reader does not apply: the public readers do
#: not agree on their signs and scales (TIGRE's says it does not know the centre of
#: rotation's sign; CIL scales CentreOfRotation* by the magnification, TIGRE does not), and
#: a wrong sign doubles the misalignment. A value other than 0 is reported (``not_used``).
XTEK_NOT_USED = ("ObjectOffsetX", "CentreOfRotationTop", "CentreOfRotationBottom",
                 "ObjectTilt", "ObjectRoll")


def read_astra_vectors(path) -> np.ndarray:
    """Rows [view, 12] (float64) of an ASTRA vector file; a bad row names its line."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: vector file not found")
    rows = []
    for k, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p for p in re.split(r"[,\s]+", text) if p]
        try:
            row = [float(p) for p in parts]
        except ValueError:
            raise DatasetError(f"{path}: line {k} (view {len(rows)}): not numbers: "
                               f"{text[:80]!r}") from None
        if len(row) != 12 or not all(math.isfinite(x) for x in row):
            raise DatasetError(f"{path}: line {k} (view {len(rows)}): expected 12 finite "
                               f"numbers, got {len(row)}")
        rows.append(row)
    if not rows:
        raise DatasetError(f"{path}: no vector rows (12 numbers per view)")
    return np.array(rows)


def _rotation(g, op, ip):
    """RTK's M_R = Rz(-ip) Rx(-op) Ry(-g) (radians): fixed -> rotated coordinates."""
    def rz(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    def rx(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return rz(-ip) @ rx(-op) @ ry(-g)


def _rtk_values(path: Path, root) -> list:
    """Per view, the dict of RTK_KEYS (global values filled in)."""
    glob = {c.tag: c.text for c in root if c.tag != "Projection"}
    radius = float(glob.get("RadiusCylindricalDetector", 0) or 0)
    if radius != 0:
        raise DatasetError(f"{path}: RadiusCylindricalDetector {radius}: cylindrical "
                           "detectors are not supported (flat panels only)")
    views = []
    for i, proj in enumerate(root.findall("Projection")):
        vals = {}
        for key in RTK_KEYS:
            el = proj.find(key)
            text = el.text if el is not None else glob.get(key)
            if text is None:
                if key not in RTK_DEFAULTS:
                    raise DatasetError(f"{path}: view {i} has no {key}")
                vals[key] = RTK_DEFAULTS[key]
                continue
            try:
                vals[key] = float(text)
            except ValueError:
                raise DatasetError(f"{path}: view {i}: {key} {text!r} is not a number") from None
            if not math.isfinite(vals[key]):
                raise DatasetError(f"{path}: view {i}: {key} must be finite")
        views.append(vals)
    if not views:
        raise DatasetError(f"{path}: no <Projection> elements")
    return views


def read_rtk_geometry(path, pixel_size, nDetector) -> tuple:
    """(mode, rows [view, 12] in mi_grg's frame, gantry angles in radians) of an RTK
    geometry XML for a detector of ``nDetector`` [v, u] pixels of ``pixel_size`` (v, u)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise DatasetError(f"{path}: not a readable RTK geometry XML ({e})") from None
    if root.tag != "RTKThreeDCircularGeometry":
        raise DatasetError(f"{path}: root element <{root.tag}>, expected "
                           "<RTKThreeDCircularGeometry>")
    views = _rtk_values(path, root)
    parallel = [v["SourceToDetectorDistance"] == 0 for v in views]
    if any(parallel) and not all(parallel):
        raise DatasetError(f"{path}: some views are parallel beam (SDD 0), others not")
    dv, du = pixel_size
    # RTK fixed (X, Y, Z) -> mi_grg (x, y, z) = (Z, X, -Y)
    to_ours = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0]])
    rows, angles = [], []
    for v in views:
        Rt = _rotation(*(math.radians(v[k]) for k in RTK_KEYS[:3])).T
        sid, sdd = v["SourceToIsocenterDistance"], v["SourceToDetectorDistance"]
        src = np.array([v["SourceOffsetX"], v["SourceOffsetY"], sid])
        det = np.array([v["ProjectionOffsetX"], v["ProjectionOffsetY"], sid - sdd])
        if all(parallel):    # the ray direction (source towards detector) in place of a source
            src, det = np.array([0, 0, -1.0]), np.array([v["ProjectionOffsetX"],
                                                         v["ProjectionOffsetY"], -sid])
        s, d = to_ours @ (Rt @ src), to_ours @ (Rt @ det)
        U = to_ours @ (Rt @ np.array([du, 0, 0]))
        V = to_ours @ (Rt @ np.array([0, dv, 0]))
        rows.append(np.concatenate([s, d, U, V]))
        angles.append(math.radians(v["GantryAngle"]))
    return ("parallel" if all(parallel) else "cone"), np.array(rows), np.array(angles)


def nominal_fields(rows: np.ndarray, nDetector, mode: str = "cone") -> dict:
    """Circular-scan fields (DSD, DSO, sDetector, angles) that best name a per-view scan:
    mean distances, the mean pixel steps and each view's source azimuth (cone) or ray
    azimuth (parallel), so that ``Geometry`` can hold the rows as its vectors."""
    s, d, U, V = rows[:, 0:3], rows[:, 3:6], rows[:, 6:9], rows[:, 9:12]
    du, dv = np.linalg.norm(U, axis=1).mean(), np.linalg.norm(V, axis=1).mean()
    nv, nu = nDetector
    if mode == "cone":
        dso = float(np.linalg.norm(s[:, :2], axis=1).mean())
        dsd = float(np.linalg.norm(d - s, axis=1).mean())
        angles = np.arctan2(s[:, 1], s[:, 0])
    else:
        dso = float(np.linalg.norm(d[:, :2], axis=1).mean()) + 1.0
        dsd = 2 * dso
        angles = np.arctan2(-s[:, 1], -s[:, 0])
    return {"mode": mode, "DSD": dsd, "DSO": dso, "sDetector": (nv * dv, nu * du),
            "angles": np.unwrap(angles)}


def _xtek_angles(path: Path, name: str, n: int):
    """Per-view angles (degrees) from ``<Name>.ang`` or ``_ctdata.txt`` beside the file,
    or None: rows whose second number is the angle, after any header lines."""
    for cand in (path.with_name(f"{name}.ang"), path.with_name("_ctdata.txt")):
        if not cand.is_file():
            continue
        vals = []
        for line in cand.read_text(errors="replace").splitlines():
            parts = re.split(r"[:\s]+", line.strip())
            try:
                nums = [float(p) for p in parts if p]
            except ValueError:
                continue
            if len(nums) >= 2:
                vals.append(nums[1])
        if len(vals) != n:
            raise DatasetError(f"{cand}: {len(vals)} angles for {n} projections")
        return np.array(vals), cand
    return None, None


def _nonzero(text: str) -> bool:
    """Whether an alignment value the reader does not apply could matter: anything but a
    number equal to 0 (an unparsable value is reported, not refused)."""
    try:
        return float(text) != 0.0
    except ValueError:
        return bool(text.strip())


def read_xtekct(path) -> dict:
    """The fields of a Nikon ``.xtekct`` file: ``geometry`` kwargs of a circular cone-beam
    ``Geometry`` (lengths in mm; nVoxel/sVoxel left to the import), ``angles`` (radians),
    ``name`` (the projections' file prefix), ``angles_from`` and ``not_used`` (the
    alignment keys of XTEK_NOT_USED that are not 0, {key: text})."""
    path = Path(path)
    cfg = configparser.ConfigParser(interpolation=None, strict=False)
    cfg.optionxform = str
    try:
        cfg.read_string(path.read_text(errors="replace"))
    except (OSError, configparser.Error) as e:
        raise DatasetError(f"{path}: not a readable .xtekct file ({e})") from None
    if "XTekCT" not in cfg:
        raise DatasetError(f"{path}: lacks the [XTekCT] section")
    sec = cfg["XTekCT"]
    missing = [k for k in XTEK_REQUIRED if k not in sec]
    if missing:
        raise DatasetError(f"{path}: lacks key(s) {missing}")

    def num(key, default=None):
        text = sec.get(key)
        if text is None:
            return default
        try:
            val = float(text)
        except ValueError:
            raise DatasetError(f"{path}: {key} = {text!r} is not a number") from None
        if not math.isfinite(val):
            raise DatasetError(f"{path}: {key} must be finite")
        return val
    n = int(num("Projections"))
    name = sec.get("Name", path.stem)
    deg, src = _xtek_angles(path, name, n)
    if deg is None:
        deg = num("InitialAngle", 0.0) + np.arange(n) * num("AngularStep", 360.0 / n)
    nu, nv = int(num("DetectorPixelsX")), int(num("DetectorPixelsY"))
    pu, pv = num("DetectorPixelSizeX"), num("DetectorPixelSizeY")
    geometry = {"mode": "cone", "DSD": num("SrcToDetector"), "DSO": num("SrcToObject"),
                "nDetector": (nv, nu), "sDetector": (nv * pv, nu * pu),
                "offDetector": (num("DetectorOffsetY", 0.0), num("DetectorOffsetX", 0.0))}
    not_used = {k: sec[k].strip() for k in XTEK_NOT_USED if k in sec and _nonzero(sec[k])}
    return {"geometry": geometry, "angles": np.radians(deg), "name": name,
            "angles_from": str(src) if src else "InitialAngle + k AngularStep",
            "not_used": not_used}


def check_rows(rows, mode, nDetector, bbox, path) -> np.ndarray:
    """``view_vectors.check_vectors`` with the file named in the error."""
    try:
        return vv.check_vectors(rows, mode, nDetector, bbox)
    except vv.VectorError as e:
        raise DatasetError(f"{path}: {e}") from None
