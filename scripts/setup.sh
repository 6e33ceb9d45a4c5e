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

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_UPDATED=""
apt_install() {
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "!! apt-get not found: install $* with your package manager and re-run" >&2
        exit 1
    fi
    if [ -z "$APT_UPDATED" ]; then $SUDO apt-get update -qq; APT_UPDATED=1; fi
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@"
}

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! have_llvm; then
    echo ">> installing Debian's libllvm19 (Dr.Jit needs libLLVM >= 16)"
    apt_install libllvm19
fi

# A venv counts as made only with pip in it: a `python -m venv` that failed for want of
# ensurepip leaves bin/python behind without pip, and the next run must repair it.
venv_ok() { [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -m pip --version >/dev/null 2>&1; }

if ! venv_ok; then
    echo ">> creating $VENV"
    if ! "$PYTHON" -m venv "$VENV"; then
        # Debian ships venv's ensurepip separately (python3-venv / python3.X-venv).
        if "$PYTHON" -c "import venv, ensurepip" >/dev/null 2>&1; then
            echo "!! $PYTHON -m venv $VENV failed (see above)" >&2
            exit 1   # not the missing-module case, which is all an apt install can fix
        fi
        PYVER=$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
        PKGS="python3-venv"
        # python3-venv covers Debian's default python3 only; $PYTHON may be another 3.X.
        if apt-cache show "python$PYVER-venv" >/dev/null 2>&1; then
            PKGS="$PKGS python$PYVER-venv"
        fi
        echo ">> $PYTHON -m venv failed (no venv/ensurepip); installing Debian's $PKGS"
        apt_install $PKGS
        "$PYTHON" -m venv "$VENV"   # on an existing half-made venv this adds what is missing
    fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[test]"
# Fail here, not later, if the package cannot find a usable LLVM.
"$VENV/bin/python" -c "import mi_grg; print('>> mi_grg', mi_grg.__version__, 'variant', mi_grg.variant())"
