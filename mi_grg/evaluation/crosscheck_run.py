"""The cross-check of a finished gr / r2 run: a volpath scene of its Gaussians in its
scanner (``run_scene``), rendered and judged as any render scene (``crosscheck.render_scene``)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry
from mi_grg.evaluation.crosscheck import render_scene
from mi_grg.evaluation.crosscheck_stats import CONFIDENCE


def run_scene(run_dir, out_dir, views: int = 2, det: int = 32, data=None) -> tuple:
    """Write ``out_dir/scene.xml``: a volpath cross-check scene of a finished gr / r2 run.

    The scanner is the run's (``metrics.json`` "geometry", in the rescaled units its
    ``gaussians.npz`` lives in), with ``det`` detector rows (columns in proportion; the
    detector's physical size is kept) and ``views`` of its test views spread evenly over
    them. Test angles come from ``data`` (the data set directory) if given, else from
    metrics.json (data sets that ``mi-grg simulate`` wrote record them), else evenly
    spaced half a step off the circle's grid (stated in the returned info).
    Returns (scene path, info dict). Raises FileNotFoundError / ValueError (one line,
    naming what is missing and how to make it)."""
    from mi_grg.data.scene import Scan, write_scan_xml
    run = Path(run_dir)
    how = (f"`mi-grg reconstruct DATA --method gr --out {run}` (or --method r2) writes it")
    if not run.is_dir():
        raise FileNotFoundError(f"run directory {run} does not exist; {how}")
    npz = run / "gaussians.npz"
    if not npz.is_file() and (run / "gaussians_before_voxel_step.npz").is_file():
        raise FileNotFoundError(f"{run} scored a voxel grid (refine_output=voxels): its "
                                "Gaussians, gaussians_before_voxel_step.npz, are not its "
                                "result, so there is no result to render as Gaussians; "
                                "rerun without refine_output=voxels to export it as "
                                "Gaussians")
    if not npz.is_file():
        resume = (" (checkpoint.npz is there: finish the run with the same command and "
                  "--resume)" if (run / "checkpoint.npz").is_file() else "")
        raise FileNotFoundError(f"{run} has no gaussians.npz, so it is not a finished gr or "
                                f"r2 run{resume}; {how}")
    metrics_path = run / "metrics.json"
    if not metrics_path.is_file():
        raise FileNotFoundError(f"{run} has no metrics.json (the run's scanner geometry); {how}")
    from mi_grg.data.inputs import read_json
    metrics = read_json(metrics_path, "metrics.json")
    g = metrics.get("geometry") if isinstance(metrics, dict) else None
    if not isinstance(g, dict):
        raise ValueError(f"{metrics_path} lacks 'geometry' (the scanner); {how}")
    views, det = int(views), int(det)
    if views < 1 or det < 1:
        raise ValueError(f"--views and --det must be >= 1, got {views} and {det}")
    given = None
    if data is not None:
        from mi_grg.data.dataset import load_case
        case = load_case(data, rescale=False)
        given = case.test_angles, f"data set {data}", case.geometry
    Gaussians.load_npz(npz)   # checked here: a broken file is named as the run's
    try:
        geo, source, pick, extent = _run_geometry(metrics, g, views, det, given)
    except (TypeError, ValueError, AttributeError, KeyError, IndexError) as e:
        named = f"{type(e).__name__}: " if isinstance(e, (KeyError, IndexError)) else ""
        raise ValueError(f"{metrics_path}: {named}{e}") from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scan = Scan(geometry=geo, object={"type": "gaussian_medium", "extent": extent,
                                      "filename": os.path.relpath(npz.resolve(), out.resolve())},
                integrator={"type": "volpath"},
                other=[{"type": "constant", "radiance": 1.0}])
    path = write_scan_xml(scan, out / "scene.xml")
    info = {"run": str(run), "method": metrics.get("method"), "angles_from": source,
            "test_view_indices": pick.astype(int).tolist()}
    return path, info


def _run_geometry(metrics: dict, g: dict, views: int, det: int, given) -> tuple:
    """(geometry of the cross-check in the run's training frame, where its angles come
    from, the test views picked, the run's truncation extent) from a run's metrics.json
    (``g``: its "geometry"); ``given``: (test angles, source, geometry) of a data set, or
    None; a per-view run needs the data set (its test views' vectors)."""
    from mi_grg.data.simulate import default_test_angles
    if g.get("per_view") and given is None:
        raise ValueError("the run's scan is per-view: pass --data DIR (the data set, whose "
                         "test views carry their vectors)")
    if given is not None:
        angles, source = given[:2]
    elif (metrics.get("data") or {}).get("scene", {}).get("test_angles"):
        angles, source = metrics["data"]["scene"]["test_angles"], "metrics.json (data.scene)"
    else:
        angles = default_test_angles(max(int(g.get("n_test_angles") or 0), views))
        source = ("evenly spaced (the run does not record its test angles; --data DIR "
                  "takes the data set's)")
    angles = np.asarray(angles, np.float64).reshape(-1)
    if angles.size == 0:
        raise ValueError(f"no test angles in {source}; pass --data DIR of a data set with "
                         "test views")
    pick = np.unique(np.round(np.linspace(0, angles.size - 1, min(views, angles.size))))
    # the Gaussians live in the rescaled frame that training used (lengths x scene_scale)
    geo = Geometry.from_scanner_dict(g, angles[pick.astype(int)]).scaled(
        float(g.get("scene_scale", 1.0)))
    nv, nu = geo.nDetector
    small = (det, max(1, round(det * nu / nv)))
    vec = None
    if given is not None and given[2].per_view:
        # the data set's rows of the picked views, in the training frame, pixels resized
        vec = given[2].scaled(float(g.get("scene_scale", 1.0))).view_vectors(
            angles[pick.astype(int)])
        vec[:, 6:9] *= nu / small[1]
        vec[:, 9:12] *= nv / small[0]
    geo = geo.replace(nDetector=small, vectors=vec)
    # the truncation extent the run trained with (the projector's 4.5 before runs recorded it)
    from mi_grg.core.projector import DEFAULT_EXTENT
    extent = float((metrics.get("method_info") or {}).get("extent", DEFAULT_EXTENT))
    return geo, source, pick, extent


def render_run(run_dir, spp: int, out_dir, views: int = 2, det: int = 32, data=None,
               seed: int = 0, confidence: float = CONFIDENCE, shown=None) -> dict:
    """``render_scene`` of the scene ``run_scene`` builds for a finished gr / r2 run."""
    path, info = run_scene(run_dir, out_dir, views=views, det=det, data=data)
    return render_scene(path, spp, out_dir, seed=seed, confidence=confidence, extra=info,
                        shown=shown)
