#!/usr/bin/env bash
# Build Unitree's Z1 software for darp's vendor-in-the-loop path (docs/hardware.md, "Vendor in the loop"):
#   z1_ctrl_sim             the vendor controller (its FSM, trajectories, safety: libZ1) with darp's simulated
#                           motors (native/z1_sim) instead of the UDP link to a real arm, SDK ports from argv
#   unitree_arm_interface   the SDK's pybind11 binding for this Python, with darp's port patch
#                           (native/z1_sim/binding-ports.patch: ArmInterface(hasGripper, ip, controllerPort, sdkPort))
# from the vendor's sources (read only; default ../shared/vendor/unitree beside the repository, or
# $DARP_Z1_VENDOR_DIR). Output: <venv>/z1_vendor/ (bin/, python/, config/), plus a .pth file that puts
# python/ on that venv's path. Rebuilt only when an input changes; safe to run concurrently (a lock).
#
# usage: scripts/build_z1_vendor.sh [PYTHON] [--quiet]      PYTHON: the venv's python (default .venv/bin/python)
# Exit 0: built or up to date; 1: one line on stderr saying why not; 3: the vendor sources are not there.
set -euo pipefail

die() { echo "build_z1_vendor: $*" >&2; exit 1; }
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
QUIET=0
PY=""
for arg in "$@"; do
    case "$arg" in
        --quiet) QUIET=1 ;;
        -*) die "unknown option $arg (usage: scripts/build_z1_vendor.sh [PYTHON] [--quiet])" ;;
        *) PY=$arg ;;
    esac
done
PY=${PY:-$REPO/.venv/bin/python}
say() { [ "$QUIET" = 1 ] || echo "build_z1_vendor: $*"; }

[ -x "$PY" ] || die "no Python at $PY (run make setup first, or pass the venv's python)"
VENDOR=${DARP_Z1_VENDOR_DIR:-$REPO/../shared/vendor/unitree}
if [ ! -f "$VENDOR/z1_controller/include/interface/IOInterface.h" ] || [ ! -d "$VENDOR/z1_sdk/lib" ]; then
    echo "build_z1_vendor: no Unitree z1_controller/ and z1_sdk/ in $VENDOR (set DARP_Z1_VENDOR_DIR)" >&2
    exit 3
fi
VENDOR=$(cd "$VENDOR" && pwd)
ARCH=$(uname -m)
[ -f "$VENDOR/z1_controller/lib/libZ1_$ARCH.so" ] || die "the vendor ships no libZ1_$ARCH.so for this machine"

# -- system packages (as scripts/ensure_system_libs.sh installs the run-time libraries) -------------------
missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
command -v g++ >/dev/null 2>&1 || missing+=(g++)
command -v make >/dev/null 2>&1 || missing+=(make)
command -v patch >/dev/null 2>&1 || missing+=(patch)
[ -f /usr/include/boost/version.hpp ] || missing+=(libboost-dev)
[ -f /usr/include/eigen3/Eigen/Core ] || missing+=(libeigen3-dev)
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        say "installing ${missing[*]}"
        export DEBIAN_FRONTEND=noninteractive
        { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}"; } >/dev/null 2>&1 \
            || die "could not install ${missing[*]} with apt-get"
    else
        die "missing ${missing[*]}: install them (apt-get install ${missing[*]}) or run as root"
    fi
fi

# -- pybind11 >= 2.13 in that Python (2.10, Debian's, builds a binding that segfaults under numpy 2) -------
pybind_ok() { "$PY" -c 'import sys, pybind11; v = tuple(int(x) for x in pybind11.__version__.split(".")[:2]); sys.exit(v < (2, 13))' 2>/dev/null; }
if ! pybind_ok; then
    say "installing pybind11>=2.13 into $PY"
    "$PY" -m pip install -q 'pybind11>=2.13' >/dev/null 2>&1 || die "pybind11 >= 2.13 is missing and pip could not install it into $PY"
    pybind_ok || die "pybind11 >= 2.13 is still not importable from $PY"
fi
PYBIND_DIR=$("$PY" -m pybind11 --cmakedir)
PYBIND_VERSION=$("$PY" -c 'import pybind11; print(pybind11.__version__)')
PREFIX=$("$PY" -c 'import sys; print(sys.prefix)')
SITE=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
EXT_SUFFIX=$("$PY" -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))')
OUT=$PREFIX/z1_vendor
mkdir -p "$OUT"

exec 9>"$OUT/.lock"
flock 9

# -- inputs: rebuild only when one changed ------------------------------------------------------------------
SRC=$REPO/native/z1_sim
hash_inputs() {
    {
        (cd "$SRC" && find . -type f ! -name '*.md' | LC_ALL=C sort | xargs sha256sum)
        (cd "$VENDOR" && find z1_controller/include z1_controller/config z1_sdk/include -type f | LC_ALL=C sort | xargs sha256sum)
        (cd "$VENDOR" && sha256sum "z1_controller/lib/libZ1_$ARCH.so" "z1_sdk/lib/libZ1_SDK_$ARCH.so" \
            z1_sdk/examples_py/arm_python_interface.cpp)
        sha256sum "$REPO/scripts/build_z1_vendor.sh"
        echo "python $("$PY" -c 'import sys; print(sys.version)') pybind11 $PYBIND_VERSION ext $EXT_SUFFIX"
        g++ --version | head -1
        cmake --version | head -1
    } | sha256sum | cut -d' ' -f1
}
STAMP=$OUT/inputs.sha256
WANT=$(hash_inputs)
BINDING=$OUT/python/unitree_arm_interface$EXT_SUFFIX
PTH=$SITE/darp_z1_vendor.pth
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ] && [ -x "$OUT/bin/z1_ctrl_sim" ] && [ -f "$BINDING" ]; then
    [ -f "$PTH" ] || echo "$OUT/python" > "$PTH"
    say "up to date: $OUT"
    exit 0
fi
rm -f "$STAMP"

# -- build ------------------------------------------------------------------------------------------------
say "building z1_ctrl_sim and unitree_arm_interface (pybind11 $PYBIND_VERSION) into $OUT"
LOG=$OUT/build.log
WORK=$OUT/build
mkdir -p "$WORK"
cp "$VENDOR/z1_sdk/examples_py/arm_python_interface.cpp" "$WORK/binding.new.cpp"
chmod u+w "$WORK/binding.new.cpp"
patch -s "$WORK/binding.new.cpp" "$SRC/binding-ports.patch" >"$LOG" 2>&1 \
    || die "darp's binding patch does not apply to this z1_sdk (log: $LOG)"
# replaced only when it changed, so that make does not recompile the binding for a controller change
if cmp -s "$WORK/binding.new.cpp" "$WORK/arm_python_interface.cpp"; then
    rm -f "$WORK/binding.new.cpp"
else
    mv "$WORK/binding.new.cpp" "$WORK/arm_python_interface.cpp"
fi
JOBS=$(nproc 2>/dev/null || echo 2)
{
    cmake -S "$SRC" -B "$WORK" -DCMAKE_BUILD_TYPE=Release -DZ1_VENDOR_DIR="$VENDOR" \
        -DBINDING_SRC="$WORK/arm_python_interface.cpp" -Dpybind11_DIR="$PYBIND_DIR" \
        -DPython_EXECUTABLE="$PY" -DPYBIND11_FINDPYTHON=ON \
        && cmake --build "$WORK" -j "$JOBS"
} >>"$LOG" 2>&1 || die "the build failed (last lines: $(tail -3 "$LOG" | tr '\n' ' ' | cut -c1-300); log: $LOG)"

# -- install: the programs beside the vendor libraries they load ($ORIGIN rpath) ---------------------------
mkdir -p "$OUT/bin" "$OUT/python" "$OUT/config"
install -m 755 "$WORK/z1_ctrl_sim" "$OUT/bin/z1_ctrl_sim"
install -m 644 "$VENDOR/z1_controller/lib/libZ1_$ARCH.so" "$OUT/bin/"
install -m 644 "$WORK/unitree_arm_interface$EXT_SUFFIX" "$BINDING"
install -m 644 "$VENDOR/z1_sdk/lib/libZ1_SDK_$ARCH.so" "$OUT/python/"
install -m 644 "$VENDOR/z1_controller/config/config.xml" "$VENDOR/z1_controller/config/savedArmStates.csv" "$OUT/config/"
echo "$OUT/python" > "$PTH"
"$PY" -c "import sys; sys.path.insert(0, '$OUT/python'); import unitree_arm_interface as u; assert u.DARP_PORTS == 1" >>"$LOG" 2>&1 \
    || die "the built binding does not import (log: $LOG)"
echo "$WANT" > "$STAMP"
say "built $OUT (z1_ctrl_sim, unitree_arm_interface for $("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])'))"
