"""Volumes in the files CT tools open: an ImageJ TIFF stack and NIfTI, with voxel size,
origin and unit (docs/conventions.md, "Volume files").

* ``npy``: the array itself, [x, y, z] float32 (no spacing; ``metrics.json`` has it).
* ``tiff``: an ImageJ hyperstack (Fiji, napari, Dragonfly), float32, pages = z slices,
  each page [y, x] (rows y, columns x); X/YResolution = 1 / dx, 1 / dy, ImageJ's
  ``spacing`` = dz, ``unit`` = the data set's length unit, ``x/y/zorigin`` (voxels) such
  that voxel index i sits at (i - origin) * spacing = its world coordinate.
* ``nifti``: ``.nii.gz`` through nibabel (3D Slicer, ITK, FSL), data [x, y, z], affine =
  diag(dx, dy, dz) plus the world position of voxel (0, 0, 0)'s centre, qform and sform
  code 1: NIfTI's RAS world is mi_grg's world (x, y, z) unchanged.

Voxel geometry comes from the scan (``sVoxel / nVoxel``, ``offOrigin``) in the data set's
length unit (mm for an imported scan; ``mi_grg.data.units``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: format name -> file suffix appended to the volume's stem ("vol_pred" -> vol_pred.tif).
FORMATS = {"npy": ".npy", "tiff": ".tif", "nifti": ".nii.gz"}
DEFAULT_FORMATS = ("npy", "tiff")

#: Length unit names -> NIfTI's xyz unit codes (nibabel's names); others are "unknown".
_NIFTI_UNITS = {"mm": "mm", "m": "meter", "um": "micron", "µm": "micron", "micron": "micron"}


def parse_formats(spec=None) -> tuple:
    """The formats to write, validated: ``spec`` is None (the default), a comma list
    ("npy,tiff") or an iterable of such strings (a repeated ``--format``). ValueError
    naming the choices for an unknown name."""
    if spec is None:
        return DEFAULT_FORMATS
    items = [spec] if isinstance(spec, str) else list(spec)
    names = [n.strip().lower() for item in items for n in str(item).split(",") if n.strip()]
    unknown = [n for n in names if n not in FORMATS]
    if unknown or not names:
        what = f"unknown format {unknown[0]!r}" if unknown else "no format given"
        raise ValueError(f"{what}; choose from {', '.join(FORMATS)} (comma list or repeated "
                         f"--format; default {','.join(DEFAULT_FORMATS)})")
    return tuple(dict.fromkeys(names))   # keep the order, drop repeats


def voxel_grid(geometry) -> dict:
    """Spacing [x, y, z] (``sVoxel / nVoxel``) and the world position of voxel (0, 0, 0)'s
    centre [x, y, z] from a ``Geometry`` or a scanner dict (``metrics.json``'s
    "geometry")."""
    if not isinstance(geometry, dict):
        geometry = geometry.to_scanner_dict()
    n = np.asarray(geometry["nVoxel"], np.float64)
    size = np.asarray(geometry["sVoxel"], np.float64)
    off = np.asarray(geometry.get("offOrigin", (0.0, 0.0, 0.0)), np.float64)
    spacing = size / n
    return {"spacing": tuple(spacing.tolist()),
            "origin": tuple((off - size / 2 + spacing / 2).tolist())}


def write_volume(out_dir, stem: str, vol: np.ndarray, geometry, unit: str,
                 formats=None) -> list:
    """Write ``vol`` [x, y, z] as ``out_dir/stem`` + each format's suffix; returns the
    paths. ``geometry``: a ``Geometry`` or scanner dict; ``unit``: its length unit."""
    vol = np.asarray(vol, dtype=np.float32)
    if vol.ndim != 3:
        raise ValueError(f"a volume must be 3-D [x, y, z], got shape {vol.shape}")
    grid = voxel_grid(geometry)
    out = Path(out_dir)
    paths = []
    for fmt in parse_formats(formats):
        path = out / f"{stem}{FORMATS[fmt]}"
        if fmt == "npy":
            np.save(path, vol)
        elif fmt == "tiff":
            write_tiff(path, vol, grid["spacing"], grid["origin"], unit)
        else:
            write_nifti(path, vol, grid["spacing"], grid["origin"], unit)
        paths.append(path)
    return paths


def write_tiff(path, vol: np.ndarray, spacing, origin, unit: str) -> None:
    """ImageJ hyperstack of ``vol`` [x, y, z]: axes ZYX, float32, calibrated."""
    import tifffile
    dx, dy, dz = (float(s) for s in spacing)
    zyx = np.ascontiguousarray(np.asarray(vol, np.float32).transpose(2, 1, 0))
    # ImageJ's origin is in voxels: world = (index - origin) * spacing.
    meta = {"axes": "ZYX", "spacing": dz, "unit": unit,
            "xorigin": -origin[0] / dx, "yorigin": -origin[1] / dy, "zorigin": -origin[2] / dz}
    tifffile.imwrite(path, zyx, imagej=True, resolution=(1.0 / dx, 1.0 / dy), metadata=meta)


def write_nifti(path, vol: np.ndarray, spacing, origin, unit: str) -> None:
    """NIfTI-1 of ``vol`` [x, y, z]: index (i, j, k) -> world (x, y, z) in RAS by the
    affine diag(spacing) + origin (qform and sform, code 1 = scanner)."""
    import nibabel as nib
    affine = np.diag([*(float(s) for s in spacing), 1.0])
    affine[:3, 3] = origin
    img = nib.Nifti1Image(np.asarray(vol, np.float32), affine)
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    img.header.set_xyzt_units(xyz=_NIFTI_UNITS.get(unit, "unknown"))
    nib.save(img, str(path))


def write_case_volume(out_dir, stem: str, vol: np.ndarray, geometry, units: dict,
                      formats=None) -> list:
    """``write_volume`` with the unit taken from a case's units block
    (``mi_grg.data.units.units_of``): "normalised" for R2-Gaussian's normalised lengths."""
    return write_volume(out_dir, stem, vol, geometry, str(units.get("length", "normalised")),
                        formats)
