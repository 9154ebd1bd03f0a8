#!/usr/bin/env bash
# Install the shared libraries darp's wheels need at run time, when they are missing and we can.
#   libusb-1.0-0   Open3D's and pyrealsense2's wheels link against it
#   libegl1 + mesa  MuJoCo's headless rendering (MUJOCO_GL=egl), osmesa as the fallback
#   libgl1, libgomp1  Open3D
set -u
missing=()
have() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have "libusb-1.0.so.0" || missing+=(libusb-1.0-0)
have "libEGL.so.1"     || missing+=(libegl1)
have "libEGL_mesa.so.0" || missing+=(libegl-mesa0)
have "libGL.so.1"      || missing+=(libgl1)
have "libOSMesa.so"    || missing+=(libosmesa6)
have "libgomp.so.1"    || missing+=(libgomp1)
if [ ${#missing[@]} -eq 0 ]; then
    exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "darp: installing system libraries: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
        || echo "darp: warning: could not install ${missing[*]}; rendering or Open3D may fail" >&2
else
    echo "darp: warning: missing system libraries ${missing[*]} (run as root or install them: apt-get install ${missing[*]})" >&2
fi
exit 0
