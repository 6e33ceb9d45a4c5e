"""Raw counts -> line integrals -log(I / I0) for ``mi-grg import``: flats and darks, or
I0 per view from free-ray columns (detected or given); the choices are recorded."""
from __future__ import annotations

import math

import numpy as np

from mi_grg.data.dataset import DatasetError
from mi_grg.data.raw_readers import mean_frame


#: Columns at each detector edge that the free-ray detection assumes the object never
#: shadows (it then grows the free region inwards from them).
EDGE_COLUMNS = 2


#: A column is free when its drift-normalised mean stays within this many noise standard
#: deviations of its median over the views (and of the free level).
FREE_RAY_SIGMAS = 8.0


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


def normalised_stack(raw, paths, opts: dict, raw_shape, record: dict) -> np.ndarray:
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
