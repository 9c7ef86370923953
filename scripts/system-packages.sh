#!/bin/sh
# System packages carotid needs beyond PyPI, on Debian/Ubuntu: an EGL/OpenGL stack (Mesa) for the
# report's off-screen pictures, the X/GLU libraries the gmsh wheel links against (core mesher), and
# Chromium for the test that opens the report in a headless browser.
# Installs only what is missing; elsewhere it says what to install and carries on.
set -e
packages="libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libglu1-mesa libxcursor1 libxft2 libxinerama1 libgomp1 chromium"
missing=""
for p in $packages; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing="$missing $p"
done
[ -z "$missing" ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "carotid: please install with your system's package manager:$missing" >&2
    exit 0
fi
if [ "$(id -u)" -eq 0 ]; then sudo=""; elif command -v sudo >/dev/null 2>&1; then sudo="sudo"; else
    echo "carotid: not root: please install$missing (apt-get)" >&2
    exit 0
fi
echo "carotid: installing system packages:$missing"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends $missing >/dev/null
