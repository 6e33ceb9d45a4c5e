"""The geometry side of ``mi-grg import``: the binned detector, the centre of rotation
(given or estimated), the default volume, the view split and the size checks."""
from __future__ import annotations

import math
import os

import numpy as np

from mi_grg.core.geometry import Geometry
from mi_grg.data.cor import estimate_cor
from mi_grg.data.dataset import DatasetError
from mi_grg.data.raw_readers import read_tiff


MAX_DEFAULT_VOXELS = 256


#: Dr.Jit indexes an array with 32-bit integers, and the projector and FDK hold a whole
#: volume or projection stack in one array.
MAX_ENTRIES = 2 ** 31


#: Float32 copies that an import holds at once: of the projection stack (counts, signal,
#: transmission, line integrals) and of the volume (FDK's accumulator, indices, result).
PROJECTION_COPIES, VOLUME_COPIES = 4, 4


#: The narrowest default cylinder, as a fraction of the one a centred axis gives: a
#: narrower one means that the axis projects near the detector's edge (a wrong --cor).
MIN_WIDTH_FRACTION = 0.25


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


def n_across(geo: Geometry, n_voxel) -> int:
    return int(n_voxel) if n_voxel is not None else min(geo.nDetector[1], MAX_DEFAULT_VOXELS)


def plan_volume(geo: Geometry, n_voxel, side, cor_label: str) -> dict:
    """nVoxel / sVoxel of the case (``default_volume``), refusing a default cylinder
    far narrower than a centred axis would give: the axis then projects near the
    detector's edge, and the volume would be a thin, tall needle."""
    try:
        vol = default_volume(geo, n_across(geo, n_voxel), side)
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


def binned_geometry(paths, angles, base, known, opts: dict) -> tuple:
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
    if base.per_view:
        return _binned_per_view(base, b, (nv_raw, nu_raw), opts), (nv_raw, nu_raw)
    geo = base.replace(nDetector=(nv_raw // b, nu_raw // b),
                       sDetector=((nv_raw // b) * b * dv, (nu_raw // b) * b * du),
                       offDetector=(base.offDetector[0] - rv / 2 * dv,
                                    base.offDetector[1] - ru / 2 * du),
                       angles=opts["angle_sign"] * angles)
    return geo, (nv_raw, nu_raw)


def _binned_per_view(base: Geometry, b: int, raw_shape, opts: dict) -> Geometry:
    """``binned_geometry`` of a per-view scan: its rows' steps x B, centres moved by half
    the dropped rows / columns."""
    if opts["angle_sign"] != 1 or opts["cor"] is not None:
        raise DatasetError("--angle-sign and --cor do not apply to a per-view geometry "
                           "(its vectors place source and detector)")
    nv_raw, nu_raw = raw_shape
    vec = base.view_vectors()
    vec[:, 3:6] -= (nu_raw % b) / 2 * vec[:, 6:9] + (nv_raw % b) / 2 * vec[:, 9:12]
    vec[:, 6:12] *= b
    (dv, du) = base.dDetector
    return base.replace(nDetector=(nv_raw // b, nu_raw // b),
                        sDetector=((nv_raw // b) * b * dv, (nu_raw // b) * b * du),
                        vectors=vec, vector_angles=None)


def given_cor(geo: Geometry, raw_shape, opts: dict) -> tuple:
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


def auto_cor(proj: np.ndarray, geo: Geometry, raw_shape, b: int) -> tuple:
    """(offDetector[1], record) estimated from the projections (``estimate_cor``)."""
    du_raw = geo.dDetector[1] / b
    crop = (raw_shape[1] % b) / 2 * du_raw
    uc, unc = estimate_cor(proj, geo.angles)
    off = (geo.nDetector[1] / 2 - uc) * geo.dDetector[1]
    return off, {"method": "auto (symmetry of the view-summed projections)",
                 "offDetector_u": off, "pixels": (off + crop) / du_raw,
                 "uncertainty_pixels": unc * b}


def cor_label(opts: dict, rec: dict) -> str:
    if opts["cor"] == "auto":
        return f"--cor auto (found {rec['pixels']:.2f} pixels)"
    return f"--cor {opts['cor']}" if opts["cor"] is not None else "offDetector[1] of the source"
