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
import sys
from pathlib import Path

import numpy as np

from mi_grg.core.geometry import Geometry, GeometryError
from mi_grg.data.case import Case
from mi_grg.data.dataset import DatasetError
from mi_grg.data.naf import NAF_LENGTH_SCALE, load_naf, naf_case
from mi_grg.data.outputs import IMPORT, check_apart, check_out, input_paths, staged
from mi_grg.data.raw_geometry import (auto_cor, binned_geometry, check_sizes, cor_label,
                                      default_memory_limit, given_cor, n_across, plan_volume,
                                      select_views)
from mi_grg.data.raw_normalise import normalise, normalised_stack  # noqa: F401 (API)
from mi_grg.data.raw_readers import check_numbering, fips_images, frame_number, parse_fips, \
    read_angles, read_stack, tiff_list


IMPORT_JSON = "import.json"


CHECK_PNG = "check.png"


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
              *input_paths(opts["scene"]), *input_paths(opts["angles"]),
              *input_paths(opts["geometry"])]
    check_out(out, IMPORT, inputs, overwrite)


def _tiff_source(source: Path, opts: dict, record: dict) -> tuple:
    """(projection paths in view order, angles (radians, before --angle-sign), the scene's
    geometry or None, the FIPS keys or None, length unit)."""
    from mi_grg.data.scene import ScanError, load_scan
    if opts.get("geometry"):
        return _geometry_file_source(source, opts, record)
    if source.suffix.lower() == ".xtekct":
        return _xtek_source(source, opts, record)
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
        if all(frame_number(p) for p in paths):
            paths = check_numbering(paths, angles.size, f"{source}: {angles.size} angles",
                                    first=min(frame_number(p)[0] for p in paths))
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


def _numbered(paths: list, n: int, what: str) -> list:
    """``paths`` in view order, ``n`` of them (numbering checked where every name has one)."""
    if len(paths) != n:
        raise DatasetError(f"{what}: {len(paths)} TIFFs for {n} views")
    if all(frame_number(p) for p in paths):
        paths = check_numbering(paths, n, f"{what}: {n} views",
                                first=min(frame_number(p)[0] for p in paths))
    return paths


def _per_view_base(mode, rows, angles, nDetector, path) -> Geometry:
    """A per-view geometry of the raw frames (the volume is planned later)."""
    from mi_grg.data.geometry_files import nominal_fields
    f = nominal_fields(rows, nDetector, mode)
    if angles is not None:
        f["angles"] = angles
    try:
        return Geometry(nDetector=nDetector, nVoxel=(1, 1, 1), sVoxel=(1e-6,) * 3,
                        vectors=rows, **f)
    except GeometryError as e:
        raise DatasetError(f"{path}: {e}") from None


def _geometry_file_source(source: Path, opts: dict, record: dict) -> tuple:
    """``--geometry FILE`` (ASTRA vectors, or RTK XML with --pixel-size) beside a TIFF
    folder / glob: (paths, nominal angles, per-view geometry, None, unit)."""
    from mi_grg.data.geometry_files import read_astra_vectors, read_rtk_geometry
    from mi_grg.data.raw_readers import read_tiff
    gpath = Path(opts["geometry"])
    if opts.get("scene"):
        raise DatasetError("give --geometry or --scene, not both")
    paths = tiff_list(source)
    shape = read_tiff(paths[0]).shape
    if gpath.suffix.lower() == ".xml":
        if opts.get("pixel_size") is None:
            raise DatasetError(f"{gpath}: an RTK geometry needs --pixel-size (its detector "
                               "pixel pitch; RTK keeps it in the projection files)")
        px = opts["pixel_size"]
        mode, rows, angles = read_rtk_geometry(gpath, (px, px), shape)
        kind = "tiff+rtk-geometry"
    else:
        rows, mode, angles, kind = read_astra_vectors(gpath), "cone", None, "tiff+astra-vectors"
    paths = _numbered(paths, len(rows), f"{source} with {gpath}")
    base = _per_view_base(mode, rows, angles, shape, gpath)
    record["source"] = {"kind": kind, "geometry": str(gpath), "views": len(rows)}
    return paths, base.angles, base, None, opts.get("unit") or "file unit"


def _xtek_source(source: Path, opts: dict, record: dict) -> tuple:
    """A Nikon ``.xtekct`` file and its ``<Name>_NNNN.tif`` projections beside it."""
    from mi_grg.data.geometry_files import read_xtekct
    if opts.get("scene") or opts.get("angles"):
        raise DatasetError(f"{source}: --scene / --angles do not apply (the .xtekct file "
                           "states the scan)")
    x = read_xtekct(source)
    paths = sorted(p for p in source.parent.iterdir()
                   if p.name.startswith(x["name"]) and p.suffix.lower() in (".tif", ".tiff"))
    paths = _numbered(paths, x["angles"].size, f"{source.parent}/{x['name']}_*.tif")
    try:
        base = Geometry(nVoxel=(1, 1, 1), sVoxel=(1e-6,) * 3, angles=x["angles"],
                        **x["geometry"])
    except GeometryError as e:
        raise DatasetError(f"{source}: {e}") from None
    record["source"] = {"kind": "xtekct", "file": str(source), "angles": x["angles_from"],
                        "not_used": x["not_used"]}
    if x["not_used"]:
        print(f"mi-grg import: {source.name} states "
              + ", ".join(f"{k} = {v}" for k, v in x["not_used"].items())
              + ": not applied (their signs differ between readers). The centre of rotation "
              + ("comes from --cor" if opts.get("cor") is not None else
                 "is DetectorOffsetX alone: give --cor auto to estimate it")
              + "; a tilted or rolled axis is not modelled.", file=sys.stderr)
    return paths, base.angles, base, None, opts.get("unit") or "mm"


def _from_tiffs(source: Path, out: Path, opts: dict, record: dict) -> tuple:
    """Raw TIFFs -> (line integrals of every view, geometry with the centre of rotation,
    length unit); sizes checked before the projections are read."""
    paths, angles, base, known, unit = _tiff_source(source, opts, record)
    check_apart(out, paths)
    geo, raw_shape = binned_geometry(paths, angles, base, known, opts)
    off, cor_rec = given_cor(geo, raw_shape, opts)
    if off is None:   # --cor auto: the cylinder is known after the estimate; a cube till then
        vox = (n_across(geo, opts["nVoxel"]),) * 3
    else:
        vox = plan_volume(geo.replace(offDetector=(geo.offDetector[0], off)), opts["nVoxel"],
                          opts["sVoxel"], cor_label(opts, {}))["nVoxel"]
    check_sizes(len(paths), geo.nDetector, vox, opts["max_memory"])
    raw = read_stack(paths, opts["bin"], raw_shape)
    record["source"]["projections"] = [str(paths[0]), str(paths[-1]), len(paths)]
    proj = normalised_stack(raw, paths, opts, raw_shape, record)
    del raw
    if off is None:
        off, cor_rec = auto_cor(proj, geo, raw_shape, opts["bin"])
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
                      cor_label(opts, record["cor"]))
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
                            ("--train-views", "train_views"), ("--geometry", "geometry"),
                            ("--pixel-size", "pixel_size")) if opts[k] is not None]
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
                unit=None, check=False, overwrite=False, max_memory=None, geometry=None,
                pixel_size=None) -> dict:
    """``mi-grg import``: see the module docstring and docs/real_data.md. Returns the
    import record (also written as OUT/import.json). Nothing is written before every
    input is checked, never into or over an input, and an existing ``out`` is replaced
    only when the new one is complete."""
    source, out = Path(source), Path(out)
    opts = _checked_options(source, dict(
        flats=flats, darks=darks, free_ray=free_ray, cor=cor, bin=bin,
        train_views=train_views, test_views=test_views, seed=seed, reference=reference,
        nVoxel=nVoxel, sVoxel=sVoxel, scene=scene, angles=angles, angle_sign=angle_sign,
        unit=unit, max_memory=default_memory_limit() if max_memory is None else max_memory,
        geometry=geometry, pixel_size=pixel_size))
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
