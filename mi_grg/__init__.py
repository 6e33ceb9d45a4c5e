"""mi_grg: sparse-view CT reconstruction with graph-based radiative Gaussians on Mitsuba 3.

Importing the package finds a libLLVM >= 16 for Dr.Jit (see ``_llvm``) and activates the
variant named by ``MI_GRG_VARIANT`` (default ``llvm_ad_mono``).
"""
from __future__ import annotations

import os as _os

from mi_grg._llvm import LLVMNotFoundError, configure_llvm as _configure_llvm

__version__ = "0.1.0"


def _one_line_if_uncaught(error: Exception) -> None:
    """A set-up error of this machine (MI_GRG_VARIANT, libLLVM) that nothing catches
    reaches the terminal as one line: the ``mi-grg`` command imports the package before
    its own error handling can run."""
    import sys
    previous = sys.excepthook

    def hook(kind, value, tb):
        if value is error:
            print(f"mi-grg: error: {value}", file=sys.stderr)
        else:
            previous(kind, value, tb)
    sys.excepthook = hook


_requested = _os.environ.get("MI_GRG_VARIANT", "llvm_ad_mono")
try:
    _configure_llvm(required=_requested.startswith("llvm"))
except LLVMNotFoundError as _e:
    _one_line_if_uncaught(_e)
    raise

import mitsuba as _mi  # noqa: E402  (after DRJIT_LIBLLVM_PATH is set)

from mi_grg.variant import (available_variants, on_set_variant, set_variant,  # noqa: E402
                            variant)


def _plugin_modules() -> list[str]:
    """Every module in plugins/ (installed as mi_grg.plugins); each registers itself."""
    import pkgutil
    import mi_grg.plugins
    return sorted(m.name for m in pkgutil.iter_modules(mi_grg.plugins.__path__)
                  if not m.name.startswith("_"))


def _register_plugins(name: str) -> None:
    """(Re)load each plugin module not yet registered for variant ``name``."""
    import importlib
    for mod in _plugin_modules():
        m = importlib.import_module("mi_grg.plugins." + mod)
        if getattr(m, "_registered_variant", None) != name:
            importlib.reload(m)


# Here, not in mi_grg.variant: the plugins import core and data, which sit above it.
on_set_variant(_register_plugins)
try:
    set_variant(_requested)
except ValueError as _e:
    from mi_grg.variant import VariantError as _VariantError
    _error = _VariantError(f"MI_GRG_VARIANT={_requested!r}: {_e}")
    _one_line_if_uncaught(_error)
    raise _error from None

from mi_grg.core.geometry import Geometry  # noqa: E402

# Public names, imported on first use so that `import mi_grg` stays light.
_LAZY = {
    "Case": "mi_grg.data.case",
    "Gaussians": "mi_grg.core.gaussians",
    "load_case": "mi_grg.data.dataset",
    "save_case": "mi_grg.data.dataset",
    "DatasetError": "mi_grg.data.dataset",
    "reconstruct": "mi_grg.methods",
    "register_method": "mi_grg.methods",
    "metrics": "mi_grg.evaluation.metrics",
    "make_phantom": "mi_grg.data.phantoms",
    "EllipsoidPhantom": "mi_grg.data.phantoms",
    "PHANTOMS": "mi_grg.data.phantoms",
    "NoiseModel": "mi_grg.data.noise",
    "simulate_case": "mi_grg.data.simulate",
    "default_geometry": "mi_grg.data.simulate",
    "project": "mi_grg.core.projector",
    "project_dr": "mi_grg.core.projector",
    "operator": "mi_grg.core.operators",
    "sart": "mi_grg.classical.iterative",
    "asd_pocs": "mi_grg.classical.iterative",
    "forward_project": "mi_grg.core.joseph",
    "back_project": "mi_grg.core.joseph",
    "voxelize": "mi_grg.core.voxelizer",
    "voxelize_dr": "mi_grg.core.voxelizer",
    "save_ply": "mi_grg.data.ply",
    "load_ply": "mi_grg.data.ply",
    "render_crosscheck": "mi_grg.evaluation.crosscheck",
    "simulate_volume_case": "mi_grg.data.volume_phantom",
    "run_experiment": "mi_grg.lab.runner",
    "write_report": "mi_grg.lab.report",
    "load_scan": "mi_grg.data.scene",
    "Scan": "mi_grg.data.scene",
    "write_scan_xml": "mi_grg.data.scene",
    "load_mitsuba_scene": "mi_grg.data.scene",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib
        module = importlib.import_module(_LAZY[name])
        return module if module.__name__.rsplit(".", 1)[-1] == name else getattr(module, name)
    raise AttributeError(f"module 'mi_grg' has no attribute {name!r}")


__all__ = ["Geometry", "LLVMNotFoundError", "available_variants", "set_variant", "variant",
           "__version__", *_LAZY]
