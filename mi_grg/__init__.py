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

__all__ = ["Geometry", "LLVMNotFoundError", "available_variants", "set_variant", "variant",
           "__version__"]
