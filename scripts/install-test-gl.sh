#!/bin/sh
# Installs Mesa's EGL and software OpenGL for the simulated lab's camera test
# (tests/lab): MuJoCo renders headless through EGL (MUJOCO_GL=egl) on Mesa's
# llvmpipe, no GPU needed. The lab's physics needs no GL at all; without
# these libraries only the camera test skips, saying why.
# Idempotent: does nothing when the libraries are already there.
set -eu

if ldconfig -p | grep -q "libEGL_mesa.so.0" && ldconfig -p | grep -q "libEGL.so.1"; then
    echo "Mesa EGL already installed"
    exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo"
    else
        echo "install-test-gl: need root (or sudo) to apt-get install Mesa's EGL" >&2
        exit 1
    fi
fi

export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update
$SUDO apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri
