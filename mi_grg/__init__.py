"""mi_grg: sparse-view CT reconstruction with graph-based radiative Gaussians on Mitsuba 3.

Importing the package finds a libLLVM >= 16 for Dr.Jit (see ``_llvm``) and activates the
variant named by ``MI_GRG_VARIANT`` (default ``llvm_ad_mono``).
"""
from __future__ import annotations

import os as _os

from ._llvm import LLVMNotFoundError, configure_llvm as _configure_llvm

__version__ = "0.1.0"

_requested = _os.environ.get("MI_GRG_VARIANT", "llvm_ad_mono")
_configure_llvm(required=_requested.startswith("llvm"))

import mitsuba as _mi  # noqa: E402  (after DRJIT_LIBLLVM_PATH is set)

from .variant import available_variants, set_variant, variant  # noqa: E402

set_variant(_requested)

from .geometry import Geometry  # noqa: E402

# Public names, imported on first use so that `import mi_grg` stays light.
_LAZY = {
    "Case": "mi_grg.case",
    "Gaussians": "mi_grg.gaussians",
    "load_case": "mi_grg.dataset",
    "save_case": "mi_grg.dataset",
    "DatasetError": "mi_grg.dataset",
    "reconstruct": "mi_grg.methods",
    "register_method": "mi_grg.methods",
    "metrics": "mi_grg.metrics",
    "make_phantom": "mi_grg.phantoms",
    "EllipsoidPhantom": "mi_grg.phantoms",
    "PHANTOMS": "mi_grg.phantoms",
    "NoiseModel": "mi_grg.noise",
    "simulate_case": "mi_grg.simulate",
    "default_geometry": "mi_grg.simulate",
    "project": "mi_grg.projector",
    "project_dr": "mi_grg.projector",
    "sart": "mi_grg.iterative",
    "asd_pocs": "mi_grg.iterative",
    "forward_project": "mi_grg.voxel_projector",
    "back_project": "mi_grg.voxel_projector",
    "voxelize": "mi_grg.voxelizer",
    "voxelize_dr": "mi_grg.voxelizer",
    "save_ply": "mi_grg.ply",
    "load_ply": "mi_grg.ply",
    "render_crosscheck": "mi_grg.crosscheck",
    "simulate_volume_case": "mi_grg.volume_phantom",
    "run_experiment": "mi_grg.experiments",
    "write_report": "mi_grg.report",
    "load_scan": "mi_grg.scene",
    "Scan": "mi_grg.scene",
    "write_scan_xml": "mi_grg.scene",
    "load_mitsuba_scene": "mi_grg.scene",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib
        module = importlib.import_module(_LAZY[name])
        return module if module.__name__ == f"mi_grg.{name}" else getattr(module, name)
    raise AttributeError(f"module 'mi_grg' has no attribute {name!r}")


__all__ = ["Geometry", "LLVMNotFoundError", "available_variants", "set_variant", "variant",
           "__version__", *_LAZY]
