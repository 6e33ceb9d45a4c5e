"""Locate a libLLVM that Dr.Jit's CPU backend can use, before Dr.Jit loads.

Dr.Jit 1.5 emits ``llvm.minimum`` intrinsics that LLVM <= 15 cannot lower ("Cannot
select fminimum"), so we need libLLVM >= 16. Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` when
its LLVM backend starts; this module sets it to the newest suitable library found.
"""
from __future__ import annotations

import glob
import os
import re
import sys

MIN_LLVM_MAJOR = 16

_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)

INSTALL_HINT = (
    "mi_grg needs libLLVM >= {min} for Dr.Jit's CPU variant (llvm_ad_mono); LLVM 15 and "
    "older crash with 'Cannot select fminimum'. Install one, e.g. on Debian/Ubuntu "
    "`sudo apt-get install libllvm19` (`make test` / `make demo` do this for you), or point "
    "DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= {min}. To use the GPU only, set "
    "MI_GRG_VARIANT=cuda_ad_mono."
).format(min=MIN_LLVM_MAJOR)


class LLVMNotFoundError(ImportError):
    """No libLLVM >= 16 was found for Dr.Jit's LLVM backend."""


def llvm_major_version(path: str) -> int | None:
    """Major version encoded in a libLLVM file name or its llvm-N directory, else None."""
    name = os.path.basename(path)
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)", r"libLLVM\.(\d+)\.dylib"):
        m = re.search(pattern, name)
        if m:
            return int(m.group(1))
    m = re.search(r"llvm[-@](\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm(search_globs=_SEARCH_GLOBS) -> str | None:
    """Path of the newest libLLVM with major version >= MIN_LLVM_MAJOR, or None."""
    best = None
    for pattern in search_globs:
        for path in glob.glob(pattern):
            major = llvm_major_version(path)
            if major is None or major < MIN_LLVM_MAJOR or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    return best[1] if best else None


def configure_llvm(required: bool = True) -> str | None:
    """Set DRJIT_LIBLLVM_PATH (unless the user set it) and return the library used.

    Raises LLVMNotFoundError with install instructions when ``required`` and none is found.
    """
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        if not os.path.isfile(user):
            raise LLVMNotFoundError(f"DRJIT_LIBLLVM_PATH={user!r} does not exist. " + INSTALL_HINT)
        major = llvm_major_version(user)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise LLVMNotFoundError(
                f"DRJIT_LIBLLVM_PATH={user!r} is LLVM {major}. " + INSTALL_HINT)
        return user
    path = find_libllvm()
    if path is None:
        if required:
            raise LLVMNotFoundError(INSTALL_HINT)
        return None
    if "drjit" in sys.modules:
        # Dr.Jit may already have started its LLVM backend with the system default.
        import warnings
        warnings.warn("drjit was imported before mi_grg; import mi_grg first (or set "
                      "DRJIT_LIBLLVM_PATH) so that Dr.Jit uses " + path, RuntimeWarning)
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path
