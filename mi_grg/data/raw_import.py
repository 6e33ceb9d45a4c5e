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
import shutil
import sys
from pathlib import Path

import numpy as np

from mi_grg.core.geometry import Geometry, GeometryError
from mi_grg.data.case import Case
from mi_grg.data.cor import estimate_cor
from mi_grg.data.dataset import DatasetError
from mi_grg.data.naf import NAF_LENGTH_SCALE, load_naf, naf_case

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
    paths.sort(key=lambda p: int(re.search(r"_(\d+)\.tiff?$", p.name, re.I).group(1)))
    if len(paths) != n:
        raise DatasetError(f"{txt}: NumberImages = {n} but {len(paths)} projection TIFFs "
                             f"{paths[0].name} ... {paths[-1].name} were found")
    return paths


def tiff_list(source: Path) -> list:
    """The TIFFs of a directory (sorted by name) or of a glob pattern."""
    if source.is_dir():
        paths = sorted(p for p in source.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
    else:
        paths = sorted(Path(p) for p in _glob.glob(str(source)))
    if not paths:
        raise DatasetError(f"{source}: no TIFF projections found")
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
            raise DatasetError(f"--free-ray {spec!r}: range {a}:{c} outside the detector's "
                                 f"{nu_raw} columns")
        cols.update(range(-(-a // b), c // b))
    if not cols:
        raise DatasetError(f"--free-ray {spec!r}: no whole binned column inside")
    return np.array(sorted(cols))


def detect_free_columns(t: np.ndarray) -> np.ndarray:
    """Border columns the object never shadows, from ``t`` [view, v, u] (counts or
    transmissions, dark subtracted).

    The outermost ``EDGE_COLUMNS`` on each side are assumed free; they give each view's
    level (removing the source's drift). Going inwards, a column stays free while its
    level-normalised mean over rows is, in every view, within ``FREE_RAY_SIGMAS`` noise
    standard deviations of the edge level; the last column before the first shadowed one
    is dropped too (penumbra)."""
    nu = t.shape[2]
    e = EDGE_COLUMNS
    if nu < 4 * e:
        raise DatasetError(f"detector has {nu} columns; free-ray detection needs >= {4 * e}")
    c = t.mean(axis=1)                                   # [view, u]
    level = np.concatenate([c[:, :e], c[:, -e:]], 1).mean(1, keepdims=True)
    if np.any(level <= 0):
        raise DatasetError("free-ray detection: an edge column is dark in some view")
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
        bad = gain <= floor
        if np.count_nonzero(bad) > 0.01 * gain.size or np.median(gain) <= floor:
            raise DatasetError(f"flats: {np.count_nonzero(bad)} of {gain.size} pixels are "
                                 "not brighter than the darks (flats darker than darks?)")
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


# ---------------------------------------------------------------- the command
def _tiff_scan(source: Path, opts: dict, record: dict) -> tuple:
    """(raw counts [view, v, u] binned, geometry (binned detector, offsets before the
    centre of rotation), raw [v, u] frame size, length unit)."""
    from mi_grg.data.scene import ScanError, load_scan
    b = opts["bin"]
    if opts.get("scene"):
        try:
            scan = load_scan(opts["scene"])
        except ScanError as e:
            raise DatasetError(str(e)) from e
        base = scan.geometry
        paths = tiff_list(source)
        angles = read_angles(opts["angles"]) if opts.get("angles") else base.angles
        if len(paths) != angles.size:
            where = (f"--angles {opts['angles']}" if opts.get("angles")
                     else f"{opts['scene']} (angles)")
            raise DatasetError(f"{source}: {len(paths)} TIFFs but {where} has "
                                 f"{angles.size} angles")
        unit = opts.get("unit") or "scene unit"
        record["source"] = {"kind": "tiff+scene", "scene": str(opts["scene"]),
                            "not_used": {k: scan.info()[k] for k in
                                         ("test_angles", "noise", "object")}}
    else:
        if opts.get("angles"):
            raise DatasetError("--angles needs --scene (a FIPS text file states its angles)")
        known, unknown = parse_fips(source)
        n = int(known["NumberImages"])
        paths = fips_images(source, n)
        angles = np.deg2rad(known["AngleFirst"] + np.arange(n) * known["AngleInterval"])
        record["source"] = {"kind": "fips", "text": str(source), "keys": known,
                            "unknown_keys": unknown}
        base = None
        unit = opts.get("unit") or "mm"
    first = read_tiff(paths[0])
    raw = read_stack(paths, b, first.shape)
    record["source"]["projections"] = [str(paths[0]), str(paths[-1]), len(paths)]
    nv_raw, nu_raw = first.shape
    if base is None:
        px = known["PixelSize"]
        base = Geometry(mode="cone", DSD=known["DistanceSourceDetector"],
                        DSO=known["DistanceSourceOrigin"], nDetector=(nv_raw, nu_raw),
                        sDetector=(nv_raw * px, nu_raw * px), nVoxel=(1, 1, 1),
                        sVoxel=(1e-3 * px,) * 3, angles=angles)
    elif tuple(base.nDetector) != (nv_raw, nu_raw):
        raise DatasetError(f"{paths[0]}: frame [v, u] = {[nv_raw, nu_raw]} but "
                             f"{opts['scene']} nDetector = {list(base.nDetector)}")
    angles = opts["angle_sign"] * angles
    # binning drops trailing rows/columns: the kept detector's centre moves by half of them
    (dv, du), rv, ru = base.dDetector, nv_raw % b, nu_raw % b
    geo = base.replace(nDetector=(nv_raw // b, nu_raw // b),
                       sDetector=((nv_raw // b) * b * dv, (nu_raw // b) * b * du),
                       offDetector=(base.offDetector[0] - rv / 2 * dv,
                                    base.offDetector[1] - ru / 2 * du), angles=angles)
    return raw, geo, (nv_raw, nu_raw), unit


def import_scan(source, out, *, flats=None, darks=None, free_ray="auto", cor=None,
                bin=1, train_views=None, test_views=0, seed=0, reference=None,
                nVoxel=None, sVoxel=None, scene=None, angles=None, angle_sign=1,
                unit=None, check=False, overwrite=False) -> dict:
    """``mi-grg import``: see the module docstring and docs/real_data.md. Returns the
    import record (also written as OUT/import.json)."""
    from mi_grg.data.dataset import _json_default, save_case
    source, out = Path(source), Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise DatasetError(f"--out {out}: exists and is not empty (use --overwrite)")
    if not source.exists() and not _glob.glob(str(source)):
        raise DatasetError(f"{source}: not found")
    if int(bin) < 1:
        raise DatasetError(f"--bin {bin}: must be an integer >= 1")
    if reference not in (None, "none", "fdk-all"):
        raise DatasetError(f"--reference {reference!r}: expected fdk-all or none")
    if angle_sign not in (1, -1):
        raise DatasetError(f"--angle-sign {angle_sign}: expected 1 or -1")
    opts = dict(flats=flats, darks=darks, free_ray=free_ray, cor=cor, bin=int(bin),
                train_views=train_views, test_views=test_views, seed=seed, reference=reference,
                nVoxel=nVoxel, sVoxel=sVoxel, scene=scene, angles=angles,
                angle_sign=angle_sign, unit=unit)
    record = {"command": "mi-grg import", "options": opts}
    is_pickle = source.suffix.lower() in (".pickle", ".pkl")

    if is_pickle:
        given = [k for k, v in (("--flats", flats), ("--darks", darks), ("--cor", cor),
                                ("--scene", scene), ("--angles", angles), ("--nVoxel", nVoxel),
                                ("--sVoxel", sVoxel), ("--train-views", train_views))
                 if v is not None] + (["--bin"] if int(bin) != 1 else []) + \
                (["--test-views"] if test_views else []) + \
                (["--free-ray"] if free_ray != "auto" else []) + \
                (["--angle-sign"] if angle_sign != 1 else [])
        if given:
            raise DatasetError(f"{source}: {', '.join(given)} do not apply to a NAF pickle "
                                 "(its projections are line integrals with their own split, "
                                 "geometry and volume)")
        case, notes = naf_case(load_naf(source), source)
        record["source"] = {"kind": "naf-pickle", "file": str(source), **notes,
                            "loader": "restricted unpickler (dicts, lists, numbers, strings, "
                                      "numpy arrays)"}
        geo_all, proj_all = case.geometry, case.train
        unit = unit or "m"
        record["source"]["length_scale"] = f"{NAF_LENGTH_SCALE} (the pickle's mm -> m)"
    else:
        raw, geo, raw_shape, unit = _tiff_scan(source, opts, record)
        b = int(bin)
        dark = flat = None
        if darks:
            dark, files = mean_frame(darks, b, raw_shape, "dark")
            record["darks"] = {"files": len(files), "first": files[0]}
        if flats:
            flat, files = mean_frame(flats, b, raw_shape, "flat")
            record["flats"] = {"files": len(files), "first": files[0]}
        if free_ray == "none":
            cols = None
        elif free_ray == "auto":
            sig = raw - (0.0 if dark is None else dark)
            if flat is not None:
                sig = sig / np.maximum(flat - (0.0 if dark is None else dark), 1e-6)
            cols = detect_free_columns(sig)
            if flat is None and len(cols) == 0:
                raise DatasetError(f"{source}: no free-ray columns found (the object "
                                     "shadows the detector's edges?); give --flats or "
                                     "--free-ray A:B,C:D")
        else:
            cols = parse_columns(free_ray, raw_shape[1], b)
        proj_all, rec = normalise(raw, dark, flat, cols)
        del raw
        rec["method"] = "flats/darks" if flat is not None else "free-ray I0 per view"
        rec["free_ray_columns"] = None if cols is None else [int(c) for c in cols]
        record["normalisation"] = rec
        # the centre of rotation: offDetector[1] (raw pixels in the record)
        # --cor PIXELS and the record count raw pixels of the whole (uncropped) detector
        du_raw = geo.dDetector[1] / b
        crop = (raw_shape[1] % b) / 2 * du_raw   # centre shift from dropped columns
        if cor == "auto":
            uc, unc = estimate_cor(proj_all, geo.angles)
            off = (geo.nDetector[1] / 2 - uc) * geo.dDetector[1]
            record["cor"] = {"method": "auto (symmetry of the view-summed projections)",
                             "offDetector_u": off, "pixels": (off + crop) / du_raw,
                             "uncertainty_pixels": unc * b}
        elif cor is not None:
            try:
                pix = float(cor)
            except ValueError:
                raise DatasetError(f"--cor {cor!r}: expected auto or a number of pixels") \
                    from None
            off = pix * du_raw - crop
            record["cor"] = {"method": "given", "pixels": pix, "offDetector_u": off}
        else:
            off = geo.offDetector[1]
            record["cor"] = {"method": "none (offDetector from the source)",
                             "offDetector_u": off}
        geo_all = geo.replace(offDetector=(geo.offDetector[0], off))

    # views
    if is_pickle:   # its own split; "all projections" = train + val
        case_geo = geo_all
        test_angles, test = case.test_angles, case.test
        train_idx = np.arange(geo_all.n_views)
        vol_geo = geo_all.with_angles(np.concatenate([geo_all.angles, test_angles]))
        proj_all = np.concatenate([case.train, test])
    else:
        a = geo_all.angles
        span = np.abs(a - a[0]) >= 2 * np.pi - 1e-6
        keep = np.flatnonzero(~span)
        if keep.size < a.size:
            record["dropped_views"] = {"indices": np.flatnonzero(span).tolist(),
                                       "why": "repeat an angle 360 degrees on"}
        proj_all, a = proj_all[keep], a[keep]
        train_idx, test_idx = select_views(a.size, train_views, int(test_views or 0), seed)
        n_vox = int(nVoxel) if nVoxel else min(geo_all.nDetector[1], MAX_DEFAULT_VOXELS)
        vol = default_volume(geo_all, n_vox, sVoxel)
        try:
            vol_geo = geo_all.replace(angles=a, **vol)
        except GeometryError as e:
            raise DatasetError(f"volume: {e}") from e
        case_geo = vol_geo.with_angles(a[train_idx])
        test_angles, test = a[test_idx], proj_all[test_idx]
        record["views"] = {"n_scan": int(a.size), "train": train_idx.tolist(),
                           "test": test_idx.tolist(), "seed": seed}
        record["volume"] = {"nVoxel": list(vol_geo.nVoxel), "sVoxel": list(vol_geo.sVoxel),
                            "rule": "given --sVoxel cube" if sVoxel else
                            "largest cylinder every view sees"}
    vol_gt = case.vol_gt if is_pickle and reference != "none" else None
    info = {"source": "mi_grg.data.raw_import", "import": IMPORT_JSON,
            "units": {"length": unit, "density": f"1/{unit}", "normalised": False}}
    if reference == "fdk-all":
        from mi_grg.classical.fdk import fdk
        vol_gt = fdk(proj_all, vol_geo)
        info["reference"] = (f"pseudo ground truth: FDK of all {vol_geo.n_views} projections "
                             "(--reference fdk-all)")
    elif vol_gt is not None:
        info["reference"] = "the pickle's image"
    record["reference"] = info.get("reference")
    out_case = Case(geometry=case_geo, train=proj_all[train_idx], test_angles=test_angles,
                    test=test, vol_gt=vol_gt, info=info)
    record["geometry"] = case_geo.to_scanner_dict()

    tmp = out.parent / f".{out.name}.import-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        save_case(out_case, tmp)
        if vol_gt is not None:   # the reference as CT tools open it, in the scan's unit
            from mi_grg.data.export import write_case_volume
            write_case_volume(tmp, "vol_gt", vol_gt, case_geo, info["units"], ("tiff", "nifti"))
        if check:
            write_check(tmp / CHECK_PNG, proj_all, vol_geo, vol_gt)
            record["check"] = CHECK_PNG
        (tmp / IMPORT_JSON).write_text(json.dumps(record, indent=2, default=_json_default))
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(old)
            tmp.rename(out)
            shutil.rmtree(old)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return record


def write_check(path, proj: np.ndarray, geo: Geometry, vol=None) -> None:
    """A montage of four normalised projections and the central FDK slice (z)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if vol is None:
        from mi_grg.classical.fdk import fdk
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
