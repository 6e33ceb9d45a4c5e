"""One switch for the Mitsuba/Dr.Jit variant: ``llvm_ad_mono`` (CPU) or ``cuda_ad_mono`` (GPU).

All mi_grg code looks up Dr.Jit types (``mi.Float``, ``mi.Point3f``...) at call time, so
the same code runs on either variant. Setting the variant also runs the hooks given to
``on_set_variant``: the package registers its Mitsuba plugins (``plugins/``) through one
(``mi_grg.__init__``), because Python plugin classes are bound to the variant that was
active when they were defined. A hook rather than an import, because the plugins sit
above ``core`` and ``data``, which set the variant themselves before they parse a scene.
"""
from __future__ import annotations

from typing import Callable

import mitsuba as mi

SUPPORTED = ("llvm_ad_mono", "cuda_ad_mono")
DEFAULT = "llvm_ad_mono"

_HOOKS: list = []


class VariantError(ValueError):
    """A variant this machine or this Mitsuba build cannot run; the message says which."""


def on_set_variant(hook: Callable[[str], None]) -> None:
    """Call ``hook(name)`` after every ``set_variant`` (once per hook)."""
    if hook not in _HOOKS:
        _HOOKS.append(hook)


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
    """Activate a variant and run the ``on_set_variant`` hooks for it (mi_grg's plugins
    register themselves for it). Returns the name."""
    if name not in SUPPORTED:
        raise VariantError(f"variant must be one of {SUPPORTED}, got {name!r}")
    if name not in mi.variants():
        raise VariantError(f"this Mitsuba build has no variant {name!r} (has "
                           f"{mi.variants()})")
    if name.startswith("cuda"):
        import drjit as dr
        if not dr.has_backend(dr.JitBackend.CUDA):
            raise VariantError("variant 'cuda_ad_mono' needs an NVIDIA GPU with a CUDA "
                               "driver; none was found. Use 'llvm_ad_mono' (CPU).")
    if mi.variant() != name:
        mi.set_variant(name)
    for hook in _HOOKS:
        hook(name)
    return name


def variant() -> str | None:
    """The active Mitsuba variant."""
    return mi.variant()
