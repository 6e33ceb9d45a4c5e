#!/usr/bin/env bash
# Set-up for a fresh Debian/Ubuntu machine: libLLVM >= 16 for Dr.Jit's CPU backend
# (LLVM 15 crashes with "Cannot select fminimum"), then a virtual environment with
# mi_grg installed in editable mode. Idempotent; `make demo` / `make test` call it.
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

have_llvm() {
    # Any libLLVM with major version >= 16 that the dynamic loader or the llvm-N dirs know.
    { ldconfig -p 2>/dev/null | awk '{print $NF}'; ls /usr/lib/llvm-*/lib/libLLVM*.so* 2>/dev/null; } |
        grep -Eq 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])|llvm-(1[6-9]|[2-9][0-9])/'
}

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! have_llvm; then
    echo ">> installing Debian's libllvm19 (Dr.Jit needs libLLVM >= 16)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo ">> creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[test]"
# Fail here, not later, if the package cannot find a usable LLVM.
"$VENV/bin/python" -c "import mi_grg; print('>> mi_grg', mi_grg.__version__, 'variant', mi_grg.variant())"
