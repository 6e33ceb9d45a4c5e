"""LLVM discovery: Dr.Jit needs libLLVM >= 16, and a clear error when there is none."""
import os
import subprocess
import sys

import pytest

from mi_grg import _llvm


@pytest.mark.parametrize("path, major", [
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15),
    ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
    ("/opt/homebrew/opt/llvm/lib/libLLVM.dylib", None),
])
def test_version_from_file_name(path, major):
    assert _llvm.llvm_major_version(path) == major


def _touch(d, name):
    p = d / name
    p.write_bytes(b"")
    return str(p)


def test_newest_suitable_library_is_chosen(tmp_path):
    _touch(tmp_path, "libLLVM-15.so")
    _touch(tmp_path, "libLLVM.so.17.1")
    best = _touch(tmp_path, "libLLVM-19.so")
    assert _llvm.find_libllvm((str(tmp_path / "libLLVM*"),)) == best


def test_only_old_llvm_is_not_enough(tmp_path):
    _touch(tmp_path, "libLLVM-15.so")
    _touch(tmp_path, "libLLVM-14.so.1")
    assert _llvm.find_libllvm((str(tmp_path / "libLLVM*"),)) is None


def test_user_path_to_old_llvm_is_rejected(tmp_path, monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", _touch(tmp_path, "libLLVM-15.so"))
    with pytest.raises(_llvm.LLVMNotFoundError, match="LLVM 15"):
        _llvm.configure_llvm()


def test_no_llvm_found_says_what_to_install(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(_llvm, "find_libllvm", lambda *a, **k: None)
    with pytest.raises(_llvm.LLVMNotFoundError, match="apt-get install libllvm19"):
        _llvm.configure_llvm(required=True)
    assert _llvm.configure_llvm(required=False) is None


def test_import_fails_clearly_without_usable_llvm(tmp_path):
    """End to end: a fresh interpreter pointed at a missing library gets our message."""
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "missing-libLLVM.so"))
    env.pop("MI_GRG_VARIANT", None)
    r = subprocess.run([sys.executable, "-c", "import mi_grg"], env=env, capture_output=True,
                       text=True)
    assert r.returncode != 0
    assert "libllvm19" in r.stderr and "DRJIT_LIBLLVM_PATH" in r.stderr
