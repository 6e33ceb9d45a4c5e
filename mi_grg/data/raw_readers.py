"""Raw scan files in: TIFF frames (binned), FIPS text files, their numbering, angle lists
(the readers of ``mi-grg import``; the pipeline is ``mi_grg.data.raw_import``)."""
from __future__ import annotations

import glob as _glob
import math
import re
import sys
from pathlib import Path

import numpy as np

from mi_grg.data.dataset import DatasetError


FIPS_REQUIRED = ("NumberImages", "AngleFirst", "AngleInterval", "AngleLast",
                 "DistanceSourceDetector", "DistanceSourceOrigin", "PixelSize")


TIFF_DTYPES = (np.uint8, np.uint16, np.float32)


def read_tiff(path) -> np.ndarray:
    """One TIFF frame [v, u] as float64 (uint8, uint16 or float32 pixels)."""
    import tifffile
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: TIFF file not found")
    try:
        img = tifffile.imread(str(path))
    except Exception as e:   # tifffile raises several types on corrupt files
        raise DatasetError(f"{path}: cannot read as TIFF ({type(e).__name__}: {e})") from e
    img = np.squeeze(img)
    if img.dtype not in TIFF_DTYPES:
        raise DatasetError(f"{path}: pixel type {img.dtype}; expected uint8, uint16 or "
                             "float32")
    if img.ndim != 2:
        raise DatasetError(f"{path}: expected one 2-D frame [v, u], got shape {img.shape}")
    img = img.astype(np.float64)
    if not np.all(np.isfinite(img)):
        raise DatasetError(f"{path}: pixels contain NaN/Inf")
    return img


def bin_frame(img: np.ndarray, b: int) -> np.ndarray:
    """Sum ``b x b`` blocks (counts add before the log); trailing rows/columns that do not
    fill a block are dropped (``geometry_for`` moves the detector centre accordingly)."""
    if b == 1:
        return img
    nv, nu = (img.shape[0] // b) * b, (img.shape[1] // b) * b
    return img[:nv, :nu].reshape(nv // b, b, nu // b, b).sum(axis=(1, 3))


def read_stack(paths, b: int = 1, shape=None, what: str = "projection") -> np.ndarray:
    """Frames ``paths`` binned by ``b`` -> float32 [n, v, u] (counts: exact up to 2^24, and
    half the memory of float64 on a real scan); every frame must have the first one's size
    (or ``shape``, the raw [v, u] size, when given)."""
    from tqdm import tqdm
    out = None
    for i, p in enumerate(tqdm(paths, desc=f"reading {what}s", disable=len(paths) < 50,
                               file=sys.stderr)):
        img = read_tiff(p)
        if shape is None:
            shape = img.shape
        if img.shape != tuple(shape):
            raise DatasetError(f"{p}: frame size [v, u] = {list(img.shape)} differs from "
                                 f"{list(shape)} (the first {what})")
        img = bin_frame(img, b)
        if out is None:
            out = np.empty((len(paths), *img.shape), np.float32)
        out[i] = img
    return out


def mean_frame(pattern: str, b: int, shape, what: str) -> tuple:
    """Mean of the frames matching ``pattern`` (binned), and the sorted file list."""
    paths = sorted(_glob.glob(pattern))
    if not paths:
        raise DatasetError(f"--{what}s {pattern}: no file matches")
    return read_stack(paths, b, shape, what).mean(axis=0), paths


def parse_fips(path) -> tuple:
    """A FIPS-style scan description ("Key = value" lines). Returns (values of the keys in
    ``FIPS_REQUIRED`` as floats, every other key as given)."""
    path = Path(path)
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read the scan description ({e})") from e
    values = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#") or "=" not in line:
            continue
        key, value = (x.strip() for x in line.split("=", 1))
        values[key] = value
    missing = [k for k in FIPS_REQUIRED if k not in values]
    if missing:
        raise DatasetError(f"{path}: lacks required key(s) {', '.join(missing)} "
                             f"(\"Key = value\" lines; needs {', '.join(FIPS_REQUIRED)})")
    known = {}
    for k in FIPS_REQUIRED:
        try:
            known[k] = float(values[k].split()[0])
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: {k} = {values[k]!r} is not a number") from None
        if not math.isfinite(known[k]):
            raise DatasetError(f"{path}: {k} = {values[k]!r} is not finite")
    for k in ("DistanceSourceDetector", "DistanceSourceOrigin", "PixelSize", "NumberImages"):
        if known[k] <= 0:
            raise DatasetError(f"{path}: {k} must be > 0, got {values[k]!r}")
    if known["NumberImages"] != round(known["NumberImages"]):
        raise DatasetError(f"{path}: NumberImages must be an integer, got "
                             f"{values['NumberImages']!r}")
    n, first, step = int(known["NumberImages"]), known["AngleFirst"], known["AngleInterval"]
    last = first + (n - 1) * step
    if abs(last - known["AngleLast"]) > 0.5 * abs(step) + 1e-9:
        raise DatasetError(f"{path}: AngleLast = {known['AngleLast']} disagrees with "
                             f"AngleFirst + (NumberImages - 1) x AngleInterval = {last}")
    return known, {k: v for k, v in values.items() if k not in FIPS_REQUIRED}


def fips_images(txt: Path, n: int) -> list:
    """The projections beside the text file: ``<name>_0001.tif ...`` where ``name`` is
    the text file's stem or, failing that, the only prefix that has numbered TIFFs."""
    groups = {}
    for p in sorted(txt.parent.iterdir()):
        m = re.fullmatch(r"(.*)_(\d{4,})\.tiff?", p.name, re.IGNORECASE)
        if m:
            groups.setdefault(m.group(1), []).append(p)
    if txt.stem in groups:
        paths = groups[txt.stem]
    elif len(groups) == 1:
        paths = next(iter(groups.values()))
    elif not groups:
        raise DatasetError(f"{txt.parent}: no projections <name>_0001.tif ... beside {txt}")
    else:
        raise DatasetError(f"{txt.parent}: several numbered TIFF series "
                             f"({', '.join(sorted(groups))}) and none named {txt.stem}_NNNN.tif")
    return check_numbering(paths, n, f"{txt}: NumberImages = {n}")


def frame_number(path: Path):
    m = re.search(r"(\d+)\.tiff?$", path.name, re.I)
    return (int(m.group(1)), len(m.group(1))) if m else None


def check_numbering(paths: list, n: int, declared: str, first=None) -> list:
    """``paths`` in view order, checked against the ``n`` views the scan declares: their
    numbers must run from ``first`` (default: 0 or 1) without a gap, a duplicate or a
    stray (a count alone would pass a gap plus a stray, and shift every angle after the
    gap)."""
    numbers = {}
    for p in paths:
        numbers.setdefault(frame_number(p)[0], []).append(p)
    dup = [ps for ps in numbers.values() if len(ps) > 1]
    if dup:
        raise DatasetError(f"{declared}: {dup[0][0].name} and {dup[0][1].name} are the same "
                           "projection number; expected one file per view")
    if first is None:
        first = 0 if 0 in numbers else 1
    expected = set(range(first, first + n))
    missing, stray = sorted(expected - set(numbers)), sorted(set(numbers) - expected)
    if missing or stray:
        p0 = paths[0]
        width = frame_number(p0)[1]
        stem = p0.name[:len(p0.name) - len(p0.suffix) - width]
        name = lambda k: f"{stem}{k:0{width}d}{p0.suffix}"  # noqa: E731
        listed = lambda ks: ", ".join(ks[:5]) + (" ..." if len(ks) > 5 else "")  # noqa: E731
        problems = []
        if missing:
            problems.append(f"missing {listed([name(k) for k in missing])}")
        if stray:
            strays = [numbers[k][0].name for k in stray]
            problems.append(f"not a view of the scan: {listed(strays)}")
        raise DatasetError(f"{declared} expects {name(first)} ... {name(first + n - 1)}; "
                           f"{'; '.join(problems)}")
    return [numbers[k][0] for k in sorted(numbers)]


def tiff_list(source: Path) -> list:
    """The TIFFs of a directory (sorted by name) or of a glob pattern."""
    if source.is_dir():
        paths = sorted(p for p in source.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
    else:
        paths = sorted(Path(p) for p in _glob.glob(str(source)))
    if not paths:
        raise DatasetError(f"{source}: no TIFF projections found")
    if all(frame_number(p) for p in paths):   # numbered: in number order (p_9 before p_10)
        paths.sort(key=lambda p: frame_number(p)[0])
    return paths


def read_angles(path) -> np.ndarray:
    """``--angles FILE``: one angle per line, in degrees -> radians."""
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except (OSError, ValueError) as e:
        raise DatasetError(f"--angles {path}: cannot read one angle (degrees) per line "
                             f"({e})") from e
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise DatasetError(f"--angles {path}: expected one finite angle (degrees) per line")
    return np.deg2rad(a)
