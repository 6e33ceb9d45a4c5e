"""Write a small synthetic raw scan, laid out like a FIPS data set, for docs/real_data.md.

    python docs/make_raw_example.py data/raw_example

writes ``scan.txt`` ("Key = value", mm and degrees), ``scan_0001.tif ... scan_0120.tif``
(uint16 photon counts of a Shepp-Logan head, 96 x 96 detector, 0.25 mm pixels), 10 flats in
``flats/`` and 10 darks in ``darks/``. The source drifts by a few per cent from view to view,
the flat field is uneven and the rotation axis projects 2.5 pixels off the detector centre,
as in a real scanner; ``mi-grg import ... --cor auto`` should report about 2.5 pixels.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import tifffile

from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.phantoms import make_phantom

N_DET, N_VIEWS, PIXEL, DSD, DSO = 96, 120, 0.25, 400.0, 250.0   # pixels, views, mm, mm, mm
SHIFT_PIXELS, I0, DENSITY = 2.5, 3.0e4, 0.2                     # -, photons, 1/mm


def main(out: Path) -> None:
    rng = np.random.default_rng(0)
    out.mkdir(parents=True, exist_ok=True)
    geo = Geometry(mode="cone", DSD=DSD, DSO=DSO, nDetector=(N_DET, N_DET),
                   sDetector=(N_DET * PIXEL,) * 2, nVoxel=(1, 1, 1), sVoxel=(10.0,) * 3,
                   offDetector=(0.0, SHIFT_PIXELS * PIXEL), angles=circular_angles(N_VIEWS))
    p = DENSITY * make_phantom("shepp").line_integrals(geo)          # [view, v, u], exact
    v, u = np.meshgrid(np.arange(N_DET), np.arange(N_DET), indexing="ij")
    flat = (1 + 0.1 * np.cos(np.pi * v / N_DET)) * (1 + 0.05 * np.sin(2 * np.pi * u / N_DET))
    dark = 100 + 10 * rng.random((N_DET, N_DET))
    drift = 1 + 0.04 * np.sin(np.arange(N_VIEWS) * 0.1)

    def counts(mean):
        return np.clip(rng.poisson(mean) + np.round(dark), 0, 65535).astype(np.uint16)

    step = 360.0 / N_VIEWS
    (out / "scan.txt").write_text(
        f"NumberImages = {N_VIEWS}\nAngleFirst = 0\nAngleInterval = {step}\n"
        f"AngleLast = {(N_VIEWS - 1) * step}\nDistanceSourceDetector = {DSD}\n"
        f"DistanceSourceOrigin = {DSO}\nPixelSize = {PIXEL}\nExposure = 100 ms\n")
    for i in range(N_VIEWS):
        tifffile.imwrite(out / f"scan_{i + 1:04d}.tif", counts(I0 * drift[i] * flat * np.exp(-p[i])))
    for name, mean in (("flats", I0 * flat), ("darks", 0 * flat)):
        (out / name).mkdir(exist_ok=True)
        for i in range(10):
            tifffile.imwrite(out / name / f"{name[:-1]}_{i:02d}.tif", counts(mean))
    print(f"wrote {out}: scan.txt, {N_VIEWS} projections, flats/, darks/")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]))
