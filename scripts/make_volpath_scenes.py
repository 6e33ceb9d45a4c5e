"""Make the data files of the shipped cross-check scenes (run once; outputs are committed).

* ``scenes/shepp_grid32.vol``: the Shepp-Logan phantom averaged onto a 32^3 grid over the
  volume box [-1, 1]^3 (``EllipsoidPhantom.voxelize``), as a Mitsuba ``.vol`` grid
  ([z, y, x, 1] float32) for ``scenes/shepp_grid_volpath.xml``.
* ``scenes/shepp_gaussians.npz``: a small gr reconstruction (24^3 Shepp-Logan, 25 noisy
  views, few Gaussians, few iterations) for ``scenes/gaussians_cone_volpath.xml``.

Usage: ``.venv/bin/python scripts/make_volpath_scenes.py`` (about a minute on 2 cores).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def make_grid(path: Path, n: int = 32) -> None:
    import mi_grg  # noqa: F401  (before mitsuba: sets the variant)
    import mitsuba as mi
    from mi_grg.data.phantoms import make_phantom
    from mi_grg.data.simulate import default_geometry
    vol = make_phantom("shepp").voxelize(default_geometry(n=n, det=8, views=1))  # [x, y, z]
    data = np.ascontiguousarray(np.transpose(vol, (2, 1, 0))[..., None], np.float32)
    mi.VolumeGrid(data).write(str(path))


def make_gaussians(path: Path) -> None:
    from mi_grg.cli import main
    with tempfile.TemporaryDirectory() as tmp:
        data, run = Path(tmp) / "data", Path(tmp) / "run"
        main(["simulate", "--phantom", "shepp", "--n", "24", "--det", "36", "--views", "25",
              "--test-views", "0", "--out", str(data)])
        main(["reconstruct", str(data), "--method", "gr", "--option", "iterations=300",
              "--option", "n_points=600", "--option", "max_gaussians=1200",
              "--option", "progress=false", "--out", str(run)])
        path.write_bytes((run / "gaussians.npz").read_bytes())


if __name__ == "__main__":
    make_grid(ROOT / "scenes" / "shepp_grid32.vol")
    make_gaussians(ROOT / "scenes" / "shepp_gaussians.npz")
    sys.exit(0)
