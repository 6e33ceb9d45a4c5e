"""One switch for the Mitsuba/Dr.Jit variant: ``llvm_ad_mono`` (CPU) or ``cuda_ad_mono`` (GPU).

All mi_grg code looks up Dr.Jit types (``mi.Float``, ``mi.Point3f``...) at call time, so
the same code runs on either variant. Setting the variant also (re)registers our Mitsuba
plugins (``plugins/``), because Python plugin classes are bound to the variant that was
active when they were defined.
"""
from __future__ import annotations

import importlib

import mitsuba as mi

SUPPORTED = ("llvm_ad_mono", "cuda_ad_mono")
DEFAULT = "llvm_ad_mono"


def plugin_modules() -> list[str]:
    """Every module in plugins/ (installed as mi_grg.plugins); each registers itself."""
    import pkgutil
    import mi_grg.plugins
    return sorted(m.name for m in pkgutil.iter_modules(mi_grg.plugins.__path__)
                  if not m.name.startswith("_"))


def available_variants() -> list[str]:
    """Supported variants that this machine can run (cuda only with a working GPU)."""
    out = []
    for name in SUPPORTED:
        if name not in mi.variants():
            continue
        if name.startswith("cuda"):
            import drjit as dr
            try:
                if not dr.has_backend(dr.JitBackend.CUDA):
                    continue
            except Exception:
                continue
        out.append(name)
    return out


def set_variant(name: str = DEFAULT) -> str:
    """Activate a variant and register mi_grg's plugins for it. Returns the name."""
    if name not in SUPPORTED:
        raise ValueError(f"variant must be one of {SUPPORTED}, got {name!r}")
    if name not in mi.variants():
        raise ValueError(f"this Mitsuba build has no variant {name!r} (has {mi.variants()})")
    if name.startswith("cuda"):
        import drjit as dr
        if not dr.has_backend(dr.JitBackend.CUDA):
            raise RuntimeError("variant 'cuda_ad_mono' needs an NVIDIA GPU with a CUDA driver; "
                               "none was found. Use 'llvm_ad_mono' (CPU).")
    if mi.variant() != name:
        mi.set_variant(name)
    for mod in plugin_modules():
        full = "mi_grg.plugins." + mod
        m = importlib.import_module(full)
        if getattr(m, "_registered_variant", None) != name:
            m = importlib.reload(m)
    return name


def variant() -> str | None:
    """The active Mitsuba variant."""
    return mi.variant()
