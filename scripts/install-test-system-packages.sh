#!/bin/sh
# Installs the system packages only tests need, each when missing:
# - Debian's chromium, for the dashboard's browser tests (tests/dashboard): they drive
#   the real page through chromium's DevTools protocol;
# - Mesa's EGL and software OpenGL, for the simulated lab's camera test (tests/lab):
#   MuJoCo renders headless through EGL (MUJOCO_GL=egl) on llvmpipe, no GPU needed.
# - coturn, a TURN server, for the video test that sends media through TURN only
#   (tests/dashboard/test_video_turn_browser.py); it runs on loopback for the test
#   and is never started as a service.
# CI needs all three; a developer without them gets clear skips. Idempotent: one
# apt-get run for whatever is missing, nothing when all is there.
set -eu

missing=""
if [ -x /usr/bin/chromium ]; then
    echo "chromium already installed: $(/usr/bin/chromium --version 2>/dev/null || echo /usr/bin/chromium)"
else
    missing="$missing chromium chromium-driver fonts-dejavu-core"
fi
if ldconfig -p | grep -q "libEGL_mesa.so.0" && ldconfig -p | grep -q "libEGL.so.1"; then
    echo "Mesa EGL already installed"
else
    missing="$missing libegl1 libegl-mesa0 libgl1-mesa-dri"
fi
if command -v turnserver >/dev/null 2>&1; then
    echo "coturn already installed"
else
    missing="$missing coturn"
fi
[ -n "$missing" ] || exit 0

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo"
    else
        echo "install-test-system-packages: need root (or sudo) to apt-get install:$missing" >&2
        exit 1
    fi
fi

export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update
# shellcheck disable=SC2086 # the package list is meant to split
$SUDO apt-get install -y --no-install-recommends $missing
