#!/usr/bin/env bash
# Set up osteonav on a fresh Debian/Ubuntu machine: the system OpenGL/EGL libraries that moderngl
# needs without a GPU (Mesa's llvmpipe), then a virtualenv with the package and its test tools.
set -euo pipefail
VENV=${1:-.venv}
PYTHON=${PYTHON:-python3}
SYS_PKGS="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libusb-1.0-0"

REQUIRED_LIBS="libEGL.so.1 libGL.so.1 libEGL_mesa.so.0 libusb-1.0.so.0"

# The linker cache is read once into a variable and searched there: piping `ldconfig -p` into
# `grep -q` under pipefail fails at random (grep exits at its first match, ldconfig dies of SIGPIPE
# and the pipeline reports the library missing). tests/test_setup_script.py runs this many times.
missing_libs() {
    local cache lib
    cache=$(ldconfig -p 2>/dev/null || true)
    for lib in "$@"; do
        case "$cache" in
            *"$lib "*) ;;
            *) echo "$lib" ;;
        esac
    done
}

# sourced (tests/test_setup_script.py): the functions only
if [ "${BASH_SOURCE[0]}" != "$0" ]; then return 0; fi
missing=0
for lib in $(missing_libs $REQUIRED_LIBS); do
    echo "setup: $lib not found"; missing=1
done
if [ "$missing" = 1 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing Mesa EGL/OpenGL: apt-get install -y $SYS_PKGS"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $SYS_PKGS
    else
        echo "setup: system libraries are missing (Mesa OpenGL/EGL for moderngl, libusb for Open3D). Install them with:" >&2
        echo "    sudo apt-get install -y $SYS_PKGS" >&2
        exit 1
    fi
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "setup: osteonav needs Python >= 3.11 (found $("$PYTHON" --version)); set PYTHON=python3.11" >&2
    exit 1
fi
if ! "$PYTHON" -c 'import venv, ensurepip' 2>/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv
    else
        echo "setup: Python's venv module is missing: sudo apt-get install -y python3-venv" >&2
        exit 1
    fi
fi
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[dev]"
echo "setup: done ($("$VENV/bin/python" -c 'import app.render.context as c; print(c.describe_default_context())' 2>/dev/null || echo 'GL context not checked'))"
