"""Real scanner data in: raw TIFF projections (FIPS text file or scene XML), flats, darks,
NAF / SAX-NeRF pickles -> a case in R2-Gaussian's layout, in the scan's own units.

Pipeline (``import_scan``; drawn in docs/real_data.md)::

    raw counts [view, v, u] (TIFF, binned by summing B x B pixels)
      -> line integrals -log(I / I0): flats/darks, or I0 per view from free-ray columns;
         counts at or below the dark floored, negative line integrals clipped (both counted)
      -> geometry: distances from the text file / scene XML, pixel size x B, the centre of
         rotation as offDetector[1] (estimated or given)
      -> views: training / test split; optional FDK-of-all-views reference volume
      -> case directory (save_case), import.json with every choice, check.png

Lengths stay in the scan's unit (mm for FIPS; m for NAF pickles, see ``mi_grg.data.naf``),
densities are then in 1/mm (1/m); the case says so in ``info["units"]`` (see
``mi_grg.data.units``). The centre of rotation estimate is ``mi_grg.data.cor``. Output is
written to a temporary directory next to ``--out`` and renamed at the end, so a failure
leaves nothing half-written.
"""
from __future__ import annotations

import glob as _glob
import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np

from mi_grg.core.geometry import Geometry, GeometryError
from mi_grg.data.case import Case
from mi_grg.data.cor import estimate_cor
from mi_grg.data.dataset import DatasetError
from mi_grg.data.naf import NAF_LENGTH_SCALE, load_naf, naf_case
from mi_grg.data.outputs import IMPORT, check_apart, check_out, input_paths, staged

IMPORT_JSON = "import.json"
CHECK_PNG = "check.png"
FIPS_REQUIRED = ("NumberImages", "AngleFirst", "AngleInterval", "AngleLast",
                 "DistanceSourceDetector", "DistanceSourceOrigin", "PixelSize")
TIFF_DTYPES = (np.uint8, np.uint16, np.float32)
#: Columns at each detector edge that the free-ray detection assumes the object never
#: shadows (it then grows the free region inwards from them).
EDGE_COLUMNS = 2
#: A column is free when its drift-normalised mean stays within this many noise standard
#: deviations of its median over the views (and of the free level).
FREE_RAY_SIGMAS = 8.0
MAX_DEFAULT_VOXELS = 256


# ---------------------------------------------------------------- reading
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


def _number(path: Path):
    m = re.search(r"(\d+)\.tiff?$", path.name, re.I)
    return (int(m.group(1)), len(m.group(1))) if m else None


def check_numbering(paths: list, n: int, declared: str, first=None) -> list:
    """``paths`` in view order, checked against the ``n`` views the scan declares: their
    numbers must run from ``first`` (default: 0 or 1) without a gap, a duplicate or a
    stray (a count alone would pass a gap plus a stray, and shift every angle after the
    gap)."""
    numbers = {}
    for p in paths:
        numbers.setdefault(_number(p)[0], []).append(p)
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
        width = _number(p0)[1]
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
    if all(_number(p) for p in paths):   # numbered: in number order (p_9 before p_10)
        paths.sort(key=lambda p: _number(p)[0])
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


# ---------------------------------------------------------------- normalisation
def parse_columns(spec: str, nu_raw: int, b: int) -> np.ndarray:
    """``--free-ray A:B,C:D`` (raw columns, half-open) -> binned columns wholly inside."""
    cols = set()
    for part in spec.split(","):
        try:
            a, c = (int(x) for x in part.split(":"))
        except ValueError:
            raise DatasetError(f"--free-ray {spec!r}: expected column ranges A:B,C:D "
                                 "(raw detector columns), 'auto' or 'none'") from None
        if not 0 <= a < c <= nu_raw:
            raise DatasetError(f"--free-ray {spec!r}: range {a}:{c}; expected A:B with "
                               f"0 <= A < B <= {nu_raw} (the detector's raw columns)")
        cols.update(range(-(-a // b), c // b))
    if not cols:
        raise DatasetError(f"--free-ray {spec!r}: no whole binned column inside")
    return np.array(sorted(cols))


def detect_free_columns(t: np.ndarray, paths=None) -> np.ndarray:
    """Border columns the object never shadows, from ``t`` [view, v, u] (counts or
    transmissions, dark subtracted).

    The outermost ``EDGE_COLUMNS`` on each side are assumed free; they give each view's
    level (removing the source's drift). Going inwards, a column stays free while its
    level-normalised mean over rows is, in every view, within ``FREE_RAY_SIGMAS`` noise
    standard deviations of the edge level; the last column before the first shadowed one
    is dropped too (penumbra). ``paths`` (the views' files) name a view in errors."""
    nu = t.shape[2]
    e = EDGE_COLUMNS
    if nu < 4 * e:
        raise DatasetError(f"--free-ray auto: the detector has {nu} columns, needs >= "
                           f"{4 * e}; give --free-ray A:B,C:D or none")
    c = t.mean(axis=1)                                   # [view, u]
    level = np.concatenate([c[:, :e], c[:, -e:]], 1).mean(1, keepdims=True)
    if np.any(level <= 0):
        k = int(np.flatnonzero(level[:, 0] <= 0)[0])
        where = paths[k] if paths is not None else f"view {k}"
        raise DatasetError(f"--free-ray auto: {where}: the edge columns are at or below the "
                           "dark level (darks brighter than the projections?); expected "
                           "free rays there, or give --free-ray A:B,C:D or none")
    n = c / level                                        # 1 where free (up to the flat)
    # Noise of one column's mean: the scatter of edge-column ratios across the views.
    ratio = c[:, 0] / c[:, -1]
    sigma = max(float(np.std(ratio / np.median(ratio))) / math.sqrt(2), 1e-6)
    ref = np.median(n[:, np.r_[:e, nu - e:nu]], axis=0).mean()
    free = np.all(np.abs(n - ref) <= FREE_RAY_SIGMAS * sigma + 2e-3 * ref, axis=0)
    cols = []
    for order in (range(nu), range(nu - 1, -1, -1)):
        run = []
        for u in order:
            if not free[u]:
                break
            run.append(u)
        cols += run[:-1] if len(run) < nu else run
    return np.array(sorted(set(cols)))


def check_flat_dark(flat, dark, opts=None, floor: float = 0.5) -> np.ndarray:
    """Pixels whose flat is not above the dark (True). More than 1 % of them, or a median
    gain at the floor, is an error: the flats and darks are swapped or wrong."""
    gain = np.asarray(flat, np.float32) - (np.float32(0) if dark is None else dark)
    bad = gain <= floor
    if np.count_nonzero(bad) > 0.01 * gain.size or np.median(gain) <= floor:
        names = (f"--flats {opts['flats']} / --darks {opts['darks']}" if opts
                 else "flats / darks")
        raise DatasetError(f"{names}: {np.count_nonzero(bad)} of {gain.size} pixels of the "
                           "mean flat are not brighter than the mean dark; expected flats "
                           "above darks (swapped?)")
    return bad


def normalise(raw: np.ndarray, dark=None, flat=None, free_cols=None, floor: float = 0.5
              ) -> tuple:
    """Line integrals -log(I / I0) [view, v, u] (float32) from counts ``raw``.

    With ``flat``: I / I0 = (raw - dark) / (flat - dark) and, with ``free_cols``, divided
    by its per-view mean over those columns (source drift). Without: I0[view, v] =
    d[view] x profile[v] from the free columns (d: per-view level, drift; profile: the
    rows' mean shape over all views). Counts at or below the dark are floored at ``floor``
    counts; negative line integrals are clipped to 0. Returns (projections, record)."""
    rec = {}
    f32 = lambda a: None if a is None else np.asarray(a, np.float32)  # noqa: E731
    raw, dark, flat, floor = f32(raw), f32(dark), f32(flat), np.float32(floor)
    sig = raw - (np.float32(0) if dark is None else dark)
    low = sig <= floor
    rec["floored_counts"] = int(np.count_nonzero(low))
    rec["floor_counts"] = float(floor)
    sig = np.where(low, floor, sig)
    if flat is not None:
        gain = flat - (np.float32(0) if dark is None else dark)
        bad = check_flat_dark(flat, dark, floor=floor)
        rec["flat_pixels_floored"] = int(np.count_nonzero(bad))
        t = sig / np.where(bad, floor, gain)
        if free_cols is not None and len(free_cols):
            drift = t[:, :, free_cols].mean(axis=(1, 2))
            t /= drift[:, None, None]
            rec["drift_per_view"] = {"min": float(drift.min()), "max": float(drift.max())}
    else:
        if free_cols is None or not len(free_cols):
            raise DatasetError("no flats given and no free-ray columns found: give --flats "
                                 "(and --darks) or --free-ray A:B,C:D")
        region = sig[:, :, free_cols].mean(axis=2)       # [view, v]
        d = region.mean(axis=1)
        profile = (region / d[:, None]).mean(axis=0)
        t = sig / (d[:, None, None] * profile[None, :, None])
        rec["drift_per_view"] = {"min": float(d.min() / d.mean()),
                                 "max": float(d.max() / d.mean())}
    p = -np.log(t)
    neg = p < 0
    rec["negative_clipped"] = int(np.count_nonzero(neg))
    rec["negative_min"] = float(p.min()) if neg.any() else 0.0
    return np.maximum(p, 0).astype(np.float32), rec


# ---------------------------------------------------------------- geometry and volume
def default_volume(geo: Geometry, n_xy: int, side=None) -> dict:
    """nVoxel / sVoxel: a cube of edge ``side``, or the largest cylinder about the axis
    that every view sees whole (radius from the detector's narrower side of the axis,
    height from its rows at the cylinder's side nearest the source); isotropic voxels,
    ``n_xy`` across."""
    if side is not None:
        return {"nVoxel": (n_xy,) * 3, "sVoxel": (float(side),) * 3}
    (nv, nu), (dv, du) = geo.nDetector, geo.dDetector
    w = nu / 2 * du - abs(geo.offDetector[1])
    h = nv / 2 * dv - abs(geo.offDetector[0])
    if w <= 0 or h <= 0:
        raise DatasetError(f"offDetector {list(geo.offDetector)} leaves no part of the "
                             "detector on one side of the axis")
    if geo.mode == "cone":
        r = geo.DSO * math.sin(math.atan(w / geo.DSD))
        zmax = h * (geo.DSO - r) / geo.DSD
    else:
        r, zmax = w, h
    nz = max(1, int(n_xy * zmax / r))
    d = 2 * r / n_xy
    return {"nVoxel": (n_xy, n_xy, nz), "sVoxel": (2 * r, 2 * r, nz * d)}


def select_views(n: int, n_train, n_test: int, seed: int) -> tuple:
    """Training views evenly spaced over the scan, test views drawn (seeded) from the rest."""
    n_train = n if n_train is None else int(n_train)
    if not 1 <= n_train <= n:
        raise DatasetError(f"--train-views {n_train}: the scan has {n} views")
    train = np.unique(np.floor(np.arange(n_train) * n / n_train).astype(int))
    rest = np.setdiff1d(np.arange(n), train)
    if not 0 <= n_test <= rest.size:
        raise DatasetError(f"--test-views {n_test}: only {rest.size} views are left after "
                             f"{train.size} training views")
    test = np.sort(np.random.default_rng(seed).choice(rest, n_test, replace=False)) \
        if n_test else np.zeros(0, int)
    return train, test


# ---------------------------------------------------------------- sizes
#: Dr.Jit indexes an array with 32-bit integers, and the projector and FDK hold a whole
#: volume or projection stack in one array.
MAX_ENTRIES = 2 ** 31
#: Float32 copies that an import holds at once: of the projection stack (counts, signal,
#: transmission, line integrals) and of the volume (FDK's accumulator, indices, result).
PROJECTION_COPIES, VOLUME_COPIES = 4, 4
#: The narrowest default cylinder, as a fraction of the one a centred axis gives: a
#: narrower one means that the axis projects near the detector's edge (a wrong --cor).
MIN_WIDTH_FRACTION = 0.25


def default_memory_limit() -> float:
    """Half of this machine's memory, GiB (``--max-memory``'s default)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 31
    except (ValueError, OSError, AttributeError):
        return 8.0


def check_sizes(n_views: int, det, vox, max_memory: float) -> dict:
    """The import's largest arrays, checked before any is allocated: each below
    ``MAX_ENTRIES`` entries, all together below ``max_memory`` GiB. Returns the record."""
    proj = int(n_views) * int(det[0]) * int(det[1])
    vol = int(np.prod([int(n) for n in vox]))
    shape_p = f"{n_views} x {det[0]} x {det[1]}"
    shape_v = " x ".join(str(int(n)) for n in vox)
    if proj >= MAX_ENTRIES:
        raise DatasetError(f"--bin: projections [view, v, u] = {shape_p} are {proj:.3g} "
                           f"values, above the {MAX_ENTRIES:.3g} one array can hold; raise --bin")
    if vol >= MAX_ENTRIES:
        raise DatasetError(f"--nVoxel: the volume {shape_v} has {vol:.3g} voxels, above the "
                           f"{MAX_ENTRIES:.3g} one array can hold; lower --nVoxel")
    gib = 4 * (PROJECTION_COPIES * proj + VOLUME_COPIES * vol) / 2 ** 30
    if gib > max_memory:
        raise DatasetError(f"--nVoxel / --bin: projections {shape_p} and volume {shape_v} "
                           f"need about {gib:.3g} GiB, above the limit of {max_memory:.3g} "
                           "GiB (--max-memory); lower --nVoxel or raise --bin")
    return {"projections": [int(n_views), int(det[0]), int(det[1])],
            "volume": [int(n) for n in vox], "memory_gib": round(gib, 4),
            "memory_limit_gib": round(float(max_memory), 4)}


def _n_across(geo: Geometry, n_voxel) -> int:
    return int(n_voxel) if n_voxel is not None else min(geo.nDetector[1], MAX_DEFAULT_VOXELS)


def plan_volume(geo: Geometry, n_voxel, side, cor_label: str) -> dict:
    """nVoxel / sVoxel of the case (``default_volume``), refusing a default cylinder
    far narrower than a centred axis would give: the axis then projects near the
    detector's edge, and the volume would be a thin, tall needle."""
    try:
        vol = default_volume(geo, _n_across(geo, n_voxel), side)
    except DatasetError as e:
        raise DatasetError(f"{cor_label}: {e}; check --cor") from None
    half = geo.nDetector[1] / 2 * geo.dDetector[1]
    if side is None and half - abs(geo.offDetector[1]) < MIN_WIDTH_FRACTION * half:
        edge = (half - abs(geo.offDetector[1])) / geo.dDetector[1]
        raise DatasetError(f"{cor_label}: the axis projects {edge:.1f} pixels from the "
                           "detector's edge, so the largest cylinder every view sees is "
                           f"{vol['sVoxel'][0]:.3g} wide and {vol['nVoxel'][2]} slices high; "
                           "check --cor or give --sVoxel")
    return vol


# ---------------------------------------------------------------- the command
def _checked_options(source: Path, opts: dict) -> dict:
    """The import's options, each checked alone (one-line errors naming the option)."""
    if not source.exists() and not _glob.glob(str(source)):
        raise DatasetError(f"{source}: not found")
    for name, key in (("--bin", "bin"), ("--nVoxel", "nVoxel")):
        value = opts[key]
        if value is not None and (int(value) != value or value < 1):
            raise DatasetError(f"{name} {value}: expected an integer >= 1")
    if opts["sVoxel"] is not None and not (math.isfinite(opts["sVoxel"]) and
                                           opts["sVoxel"] > 0):
        raise DatasetError(f"--sVoxel {opts['sVoxel']}: expected a length > 0")
    if opts["reference"] not in (None, "none", "fdk-all"):
        raise DatasetError(f"--reference {opts['reference']!r}: expected fdk-all or none")
    if opts["angle_sign"] not in (1, -1):
        raise DatasetError(f"--angle-sign {opts['angle_sign']}: expected 1 or -1")
    if opts["cor"] not in (None, "auto"):
        try:
            pixels = float(opts["cor"])
        except ValueError:
            pixels = math.nan
        if not math.isfinite(pixels):
            raise DatasetError(f"--cor {opts['cor']!r}: expected auto or a number of pixels")
    if not (opts["max_memory"] > 0):
        raise DatasetError(f"--max-memory {opts['max_memory']}: expected GiB > 0")
    return {**opts, "bin": int(opts["bin"])}


def _check_out(out: Path, source: Path, opts: dict, overwrite: bool) -> None:
    """--out must be writable, apart from every input (the folders of the scan, its flats
    and darks included), and replaceable if it exists."""
    frames = [*input_paths(opts["flats"]), *input_paths(opts["darks"])]
    if source.suffix.lower() not in (".pickle", ".pkl"):
        frames += input_paths(source)
    inputs = [source, *frames, *{p.parent for p in frames if p.is_file()},
              *input_paths(opts["scene"]), *input_paths(opts["angles"])]
    check_out(out, IMPORT, inputs, overwrite)


def _tiff_source(source: Path, opts: dict, record: dict) -> tuple:
    """(projection paths in view order, angles (radians, before --angle-sign), the scene's
    geometry or None, the FIPS keys or None, length unit)."""
    from mi_grg.data.scene import ScanError, load_scan
    if opts.get("scene"):
        try:
            scan = load_scan(opts["scene"])
        except ScanError as e:
            raise DatasetError(str(e)) from e
        paths = tiff_list(source)
        angles = read_angles(opts["angles"]) if opts.get("angles") else scan.geometry.angles
        if len(paths) != angles.size:
            where = (f"--angles {opts['angles']}" if opts.get("angles")
                     else f"{opts['scene']} (angles)")
            raise DatasetError(f"{source}: {len(paths)} TIFFs but {where} has "
                               f"{angles.size} angles")
        if all(_number(p) for p in paths):
            paths = check_numbering(paths, angles.size, f"{source}: {angles.size} angles",
                                    first=min(_number(p)[0] for p in paths))
        record["source"] = {"kind": "tiff+scene", "scene": str(opts["scene"]),
                            "not_used": {k: scan.info()[k] for k in
                                         ("test_angles", "noise", "object")}}
        return paths, angles, scan.geometry, None, opts.get("unit") or "scene unit"
    if opts.get("angles"):
        raise DatasetError("--angles needs --scene (a FIPS text file states its angles)")
    known, unknown = parse_fips(source)
    n = int(known["NumberImages"])
    paths = fips_images(source, n)
    angles = np.deg2rad(known["AngleFirst"] + np.arange(n) * known["AngleInterval"])
    record["source"] = {"kind": "fips", "text": str(source), "keys": known,
                        "unknown_keys": unknown}
    return paths, angles, None, known, opts.get("unit") or "mm"


def _binned_geometry(paths, angles, base, known, opts: dict) -> tuple:
    """(geometry with the binned detector and offsets before the centre of rotation,
    raw [v, u] frame size), from the first frame's size alone."""
    b = opts["bin"]
    nv_raw, nu_raw = read_tiff(paths[0]).shape
    if b > min(nv_raw, nu_raw):
        raise DatasetError(f"--bin {b}: larger than the {nv_raw} x {nu_raw} pixel frames of "
                           f"{paths[0]}")
    if base is None:
        px = known["PixelSize"]
        base = Geometry(mode="cone", DSD=known["DistanceSourceDetector"],
                        DSO=known["DistanceSourceOrigin"], nDetector=(nv_raw, nu_raw),
                        sDetector=(nv_raw * px, nu_raw * px), nVoxel=(1, 1, 1),
                        sVoxel=(1e-3 * px,) * 3, angles=angles)
    elif tuple(base.nDetector) != (nv_raw, nu_raw):
        raise DatasetError(f"{paths[0]}: frame [v, u] = {[nv_raw, nu_raw]} but "
                           f"{opts['scene']} nDetector = {list(base.nDetector)}")
    # binning drops trailing rows/columns: the kept detector's centre moves by half of them
    (dv, du), rv, ru = base.dDetector, nv_raw % b, nu_raw % b
    geo = base.replace(nDetector=(nv_raw // b, nu_raw // b),
                       sDetector=((nv_raw // b) * b * dv, (nu_raw // b) * b * du),
                       offDetector=(base.offDetector[0] - rv / 2 * dv,
                                    base.offDetector[1] - ru / 2 * du),
                       angles=opts["angle_sign"] * angles)
    return geo, (nv_raw, nu_raw)


def _given_cor(geo: Geometry, raw_shape, opts: dict) -> tuple:
    """(offDetector[1], record) for --cor PIXELS or none; (None, None) for --cor auto."""
    cor, b = opts["cor"], opts["bin"]
    du_raw = geo.dDetector[1] / b
    if cor == "auto":
        return None, None
    if cor is None:
        return geo.offDetector[1], {"method": "none (offDetector from the source)",
                                    "offDetector_u": geo.offDetector[1]}
    pix = float(cor)
    off = pix * du_raw - (raw_shape[1] % b) / 2 * du_raw   # dropped columns move the centre
    return off, {"method": "given", "pixels": pix, "offDetector_u": off}


def _auto_cor(proj: np.ndarray, geo: Geometry, raw_shape, b: int) -> tuple:
    """(offDetector[1], record) estimated from the projections (``estimate_cor``)."""
    du_raw = geo.dDetector[1] / b
    crop = (raw_shape[1] % b) / 2 * du_raw
    uc, unc = estimate_cor(proj, geo.angles)
    off = (geo.nDetector[1] / 2 - uc) * geo.dDetector[1]
    return off, {"method": "auto (symmetry of the view-summed projections)",
                 "offDetector_u": off, "pixels": (off + crop) / du_raw,
                 "uncertainty_pixels": unc * b}


def _cor_label(opts: dict, rec: dict) -> str:
    if opts["cor"] == "auto":
        return f"--cor auto (found {rec['pixels']:.2f} pixels)"
    return f"--cor {opts['cor']}" if opts["cor"] is not None else "offDetector[1] of the source"


def _normalised(raw, paths, opts: dict, raw_shape, record: dict) -> np.ndarray:
    """Line integrals from the raw counts: flats/darks (checked against each other first)
    and free-ray columns as the options say; the choices go into ``record``."""
    b, free_ray = opts["bin"], opts["free_ray"]
    dark = flat = None
    if opts["darks"]:
        dark, files = mean_frame(opts["darks"], b, raw_shape, "dark")
        record["darks"] = {"files": len(files), "first": files[0]}
    if opts["flats"]:
        flat, files = mean_frame(opts["flats"], b, raw_shape, "flat")
        record["flats"] = {"files": len(files), "first": files[0]}
        check_flat_dark(flat, dark, opts)
    if free_ray == "none":
        cols = None
    elif free_ray == "auto":
        sig = raw - (0.0 if dark is None else dark)
        if flat is not None:
            sig = sig / np.maximum(flat - (0.0 if dark is None else dark), 1e-6)
        cols = detect_free_columns(sig, paths)
        if flat is None and len(cols) == 0:
            raise DatasetError(f"{paths[0].parent}: no free-ray columns found (the object "
                               "shadows the detector's edges?); give --flats or "
                               "--free-ray A:B,C:D")
    else:
        cols = parse_columns(free_ray, raw_shape[1], b)
    proj, rec = normalise(raw, dark, flat, cols)
    rec["method"] = "flats/darks" if flat is not None else "free-ray I0 per view"
    rec["free_ray_columns"] = None if cols is None else [int(c) for c in cols]
    record["normalisation"] = rec
    return proj


def _from_tiffs(source: Path, out: Path, opts: dict, record: dict) -> tuple:
    """Raw TIFFs -> (line integrals of every view, geometry with the centre of rotation,
    length unit); sizes checked before the projections are read."""
    paths, angles, base, known, unit = _tiff_source(source, opts, record)
    check_apart(out, paths)
    geo, raw_shape = _binned_geometry(paths, angles, base, known, opts)
    off, cor_rec = _given_cor(geo, raw_shape, opts)
    if off is None:   # --cor auto: the cylinder is known after the estimate; a cube till then
        vox = (_n_across(geo, opts["nVoxel"]),) * 3
    else:
        vox = plan_volume(geo.replace(offDetector=(geo.offDetector[0], off)), opts["nVoxel"],
                          opts["sVoxel"], _cor_label(opts, {}))["nVoxel"]
    check_sizes(len(paths), geo.nDetector, vox, opts["max_memory"])
    raw = read_stack(paths, opts["bin"], raw_shape)
    record["source"]["projections"] = [str(paths[0]), str(paths[-1]), len(paths)]
    proj = _normalised(raw, paths, opts, raw_shape, record)
    del raw
    if off is None:
        off, cor_rec = _auto_cor(proj, geo, raw_shape, opts["bin"])
    record["cor"] = cor_rec
    return proj, geo.replace(offDetector=(geo.offDetector[0], off)), unit


def _tiff_views(proj_all, geo_all: Geometry, opts: dict, record: dict) -> tuple:
    """(projections of the kept views, volume geometry with their angles, training and
    test indices into them): a view 360 degrees after the first is dropped."""
    a = geo_all.angles
    span = np.abs(a - a[0]) >= 2 * np.pi - 1e-6
    keep = np.flatnonzero(~span)
    if keep.size < a.size:
        record["dropped_views"] = {"indices": np.flatnonzero(span).tolist(),
                                   "why": "repeat an angle 360 degrees on"}
    proj_all, a = proj_all[keep], a[keep]
    train_idx, test_idx = select_views(a.size, opts["train_views"],
                                       int(opts["test_views"] or 0), opts["seed"])
    vol = plan_volume(geo_all, opts["nVoxel"], opts["sVoxel"],
                      _cor_label(opts, record["cor"]))
    record["sizes"] = check_sizes(a.size, geo_all.nDetector, vol["nVoxel"],
                                  opts["max_memory"])
    try:
        vol_geo = geo_all.replace(angles=a, **vol)
    except GeometryError as e:
        raise DatasetError(f"volume: {e}") from e
    record["views"] = {"n_scan": int(a.size), "train": train_idx.tolist(),
                       "test": test_idx.tolist(), "seed": opts["seed"]}
    record["volume"] = {"nVoxel": list(vol_geo.nVoxel), "sVoxel": list(vol_geo.sVoxel),
                        "rule": "given --sVoxel cube" if opts["sVoxel"] else
                        "largest cylinder every view sees"}
    return proj_all, vol_geo, train_idx, test_idx


def _pickle_options_given(opts: dict) -> list:
    given = [f for f, k in (("--flats", "flats"), ("--darks", "darks"), ("--cor", "cor"),
                            ("--scene", "scene"), ("--angles", "angles"),
                            ("--nVoxel", "nVoxel"), ("--sVoxel", "sVoxel"),
                            ("--train-views", "train_views")) if opts[k] is not None]
    return given + [f for f, bad in (("--bin", opts["bin"] != 1),
                                     ("--test-views", bool(opts["test_views"])),
                                     ("--free-ray", opts["free_ray"] != "auto"),
                                     ("--angle-sign", opts["angle_sign"] != 1)) if bad]


def _from_pickle(source: Path, opts: dict, record: dict) -> tuple:
    """(the pickle's case, all projections, their volume geometry, unit)."""
    given = _pickle_options_given(opts)
    if given:
        raise DatasetError(f"{source}: {', '.join(given)} do not apply to a NAF pickle "
                           "(its projections are line integrals with their own split, "
                           "geometry and volume)")
    case, notes = naf_case(load_naf(source), source)
    record["source"] = {"kind": "naf-pickle", "file": str(source), **notes,
                        "loader": "restricted unpickler (dicts, lists, numbers, strings, "
                                  "numpy arrays)",
                        "length_scale": f"{NAF_LENGTH_SCALE} (the pickle's mm -> m)"}
    geo = case.geometry
    record["sizes"] = check_sizes(geo.n_views + len(case.test_angles), geo.nDetector,
                                  geo.nVoxel, opts["max_memory"])
    vol_geo = geo.with_angles(np.concatenate([geo.angles, case.test_angles]))
    return case, np.concatenate([case.train, case.test]), vol_geo, opts["unit"] or "m"


def _reference(proj_all, vol_geo: Geometry, opts: dict, vol_gt, unit: str) -> tuple:
    """(reference volume or None, the case's info)."""
    info = {"source": "mi_grg.data.raw_import", "import": IMPORT_JSON,
            "units": {"length": unit, "density": f"1/{unit}", "normalised": False}}
    if opts["reference"] == "fdk-all":
        from mi_grg.core.fdk import fdk
        vol_gt = fdk(proj_all, vol_geo)
        info["reference"] = (f"pseudo ground truth: FDK of all {vol_geo.n_views} projections "
                             "(--reference fdk-all)")
    elif vol_gt is not None:
        info["reference"] = "the pickle's image"
    return vol_gt, info


def _write(out: Path, case: Case, record: dict, check: bool, proj_all, vol_geo) -> None:
    """The case, import.json and check.png, replacing ``out`` only once all are written."""
    from mi_grg.data.dataset import json_default, save_case
    with staged(out, IMPORT) as tmp:
        save_case(case, tmp)
        if case.vol_gt is not None:   # the reference as CT tools open it, in the scan's unit
            from mi_grg.data.export import write_case_volume
            write_case_volume(tmp, "vol_gt", case.vol_gt, case.geometry,
                              case.info["units"], ("tiff", "nifti"))
        if check:
            write_check(tmp / CHECK_PNG, proj_all, vol_geo, case.vol_gt)
            record["check"] = CHECK_PNG
        (tmp / IMPORT_JSON).write_text(json.dumps(record, indent=2, default=json_default))


def import_scan(source, out, *, flats=None, darks=None, free_ray="auto", cor=None,
                bin=1, train_views=None, test_views=0, seed=0, reference=None,
                nVoxel=None, sVoxel=None, scene=None, angles=None, angle_sign=1,
                unit=None, check=False, overwrite=False, max_memory=None) -> dict:
    """``mi-grg import``: see the module docstring and docs/real_data.md. Returns the
    import record (also written as OUT/import.json). Nothing is written before every
    input is checked, never into or over an input, and an existing ``out`` is replaced
    only when the new one is complete."""
    source, out = Path(source), Path(out)
    opts = _checked_options(source, dict(
        flats=flats, darks=darks, free_ray=free_ray, cor=cor, bin=bin,
        train_views=train_views, test_views=test_views, seed=seed, reference=reference,
        nVoxel=nVoxel, sVoxel=sVoxel, scene=scene, angles=angles, angle_sign=angle_sign,
        unit=unit, max_memory=default_memory_limit() if max_memory is None else max_memory))
    _check_out(out, source, opts, overwrite)
    record = {"command": "mi-grg import", "options": opts}
    if source.suffix.lower() in (".pickle", ".pkl"):   # its own split; all = train + val
        case, proj_all, vol_geo, unit = _from_pickle(source, opts, record)
        case_geo, test_angles, test = case.geometry, case.test_angles, case.test
        train_idx, vol_gt = np.arange(case_geo.n_views), case.vol_gt
        if opts["reference"] == "none":
            vol_gt = None
    else:
        proj_all, geo_all, unit = _from_tiffs(source, out, opts, record)
        proj_all, vol_geo, train_idx, test_idx = _tiff_views(proj_all, geo_all, opts, record)
        case_geo = vol_geo.with_angles(vol_geo.angles[train_idx])
        test_angles, test, vol_gt = vol_geo.angles[test_idx], proj_all[test_idx], None
    vol_gt, info = _reference(proj_all, vol_geo, opts, vol_gt, unit)
    record["reference"] = info.get("reference")
    record["geometry"] = case_geo.to_scanner_dict()
    out_case = Case(geometry=case_geo, train=proj_all[train_idx], test_angles=test_angles,
                    test=test, vol_gt=vol_gt, info=info)
    _write(out, out_case, record, check, proj_all, vol_geo)
    return record


def write_check(path, proj: np.ndarray, geo: Geometry, vol=None) -> None:
    """A montage of four normalised projections and the central FDK slice (z)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if vol is None:
        from mi_grg.core.fdk import fdk
        nx, ny, nz = geo.nVoxel
        dz = geo.dVoxel[2]
        vol = fdk(proj, geo.replace(nVoxel=(nx, ny, 1), sVoxel=(*geo.sVoxel[:2], dz)))
    idx = np.linspace(0, proj.shape[0], 4, endpoint=False).astype(int)
    fig, ax = plt.subplots(1, 5, figsize=(16, 3.6))
    for a, i in zip(ax[:4], idx):
        im = a.imshow(proj[i], cmap="gray")
        a.set_title(f"view {i}: {np.degrees(geo.angles[i]):.1f} deg\n[v, u], -log(I/I0)")
        fig.colorbar(im, ax=a, fraction=0.046)
    sl = vol[:, :, vol.shape[2] // 2].T
    im = ax[4].imshow(sl, cmap="gray", origin="lower")
    ax[4].set_title("FDK, central z slice\n(x right, y up)")
    fig.colorbar(im, ax=ax[4], fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
