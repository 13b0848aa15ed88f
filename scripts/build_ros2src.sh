#!/usr/bin/env bash
# Build the ROS 2 Jazzy packages that no Python wheel provides -- tf2_msgs, tf2, tf2_py,
# composition_interfaces and tf2_ros_py (tf2_ros) -- from their released sources (SRC, e.g.
# ../shared/ros2src) into VENV, with CMake against the ament prefix that the ROS wheels install
# there (the way the wheels themselves were built).
#   bash scripts/build_ros2src.sh VENV SRC
# Cached: VENV/.bev_ros2src_built holds a hash of SRC and this script; nothing is rebuilt while
# it matches (and the packages import). Progress and errors go to stderr, the tools' output to
# stdout (scripts/setup_venv.sh sends it to its log). Exit 0 when the packages import
# afterwards, non-zero with the reason otherwise. One build at a time per venv (a lock file).
set -euo pipefail
venv="$(cd "${1:?usage: build_ros2src.sh VENV SRC}" && pwd)"
src="$(cd "${2:?usage: build_ros2src.sh VENV SRC}" && pwd)"
py="$venv/bin/python"
stamp="$venv/.bev_ros2src_built"
here="$(cd "$(dirname "$0")" && pwd)"
# The hash: every source file's content and path, and this script.
want=$( (cd "$src" && find . -type f ! -name '*.pyc' -print0 | LC_ALL=C sort -z | xargs -0 sha256sum;
         cat "$here/build_ros2src.sh") | sha256sum | cut -c1-16)
probe="import tf2_msgs.msg, tf2_py, tf2_ros, composition_interfaces.srv"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && "$py" -c "$probe" 2>/dev/null; then
  exit 0
fi
exec 9>"$venv/.bev_ros2src.lock"
flock 9  # a concurrent set-up waits for this one, then finds the stamp
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && "$py" -c "$probe" 2>/dev/null; then
  exit 0
fi
echo "building tf2_msgs, tf2, tf2_py, composition_interfaces and tf2_ros from $src into $venv" \
     "(about 2-4 minutes with 2 cores; once, until the sources change)" >&2
rm -f "$stamp"
for tool in cmake make c++; do
  command -v "$tool" >/dev/null || { echo "error: '$tool' not found (cmake, make and a C++ compiler build tf2)" >&2; exit 3; }
done
"$py" -c "import rclpy" 2>/dev/null || { echo "error: $venv lacks rclpy (the ROS 2 Jazzy wheels come first)" >&2; exit 2; }
# 1. The build tools as wheels: ament_cmake (no linters), the rosidl generators, python_cmake_module.
ament=(ament-cmake ament-cmake-core ament-cmake-export-definitions ament-cmake-export-dependencies
       ament-cmake-export-include-directories ament-cmake-export-interfaces ament-cmake-export-libraries
       ament-cmake-export-link-flags ament-cmake-export-targets ament-cmake-gen-version-h ament-cmake-gmock
       ament-cmake-gtest ament-cmake-include-directories ament-cmake-libraries ament-cmake-pytest
       ament-cmake-python ament-cmake-ros ament-cmake-target-dependencies ament-cmake-test
       ament-cmake-vendor-package ament-cmake-version gmock-vendor gtest-vendor domain-coordinator
       python-cmake-module fastrtps-cmake-module rmw-implementation-cmake ament-package
       rosidl-adapter rosidl-cli rosidl-cmake rosidl-core-generators rosidl-default-generators
       rosidl-generator-c rosidl-generator-cpp rosidl-generator-py rosidl-generator-type-description
       rosidl-parser rosidl-pycommon rosidl-typesupport-c rosidl-typesupport-cpp
       rosidl-typesupport-fastrtps-c rosidl-typesupport-fastrtps-cpp rosidl-typesupport-interface
       rosidl-typesupport-introspection-c rosidl-typesupport-introspection-cpp)
"$py" -m pip install -q catkin_pkg "empy==3.3.4" lark numpy wheel "setuptools<80" "${ament[@]/#/ros-jazzy-}"
# 2. The wheels' exported CMake files name the include folders of the machine that built them;
#    point them at this venv's Python and numpy (else: "Imported target ... non-existent path").
"$py" - "$venv" <<'PY'
import glob, sys, sysconfig
import numpy
venv = sys.argv[1]
py_inc, np_inc = sysconfig.get_paths()["include"], numpy.get_include()
for path in glob.glob(f"{venv}/share/*/cmake/*.cmake"):
    text = open(path).read()
    new = text.replace("/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include", np_inc)
    new = new.replace("/opt/python/cp311-cp311/include/python3.11", py_inc)
    if new != text:
        open(path, "w").write(new)
PY
# 3. CMake builds from a writable copy (SRC may be read-only), in dependency order.
work="$(mktemp -d)"; trap 'rm -rf "$work"' EXIT
cp -r "$src"/. "$work"/ && chmod -R u+w "$work"
export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
for p in tf2_msgs tf2 tf2_py composition_interfaces; do
  echo "  building $p" >&2
  mkdir -p "$work/_build/$p"
  (cd "$work/_build/$p" &&
   cmake "$work/$p" -DCMAKE_INSTALL_PREFIX="$venv" -DPython3_EXECUTABLE="$py" -DBUILD_TESTING=OFF \
         -DCMAKE_BUILD_TYPE=Release &&
   make -j"$(nproc)" && make install) || { echo "error: building $p failed" >&2; exit 4; }
done
"$py" -m pip install -q --no-deps --no-build-isolation "$work/tf2_ros_py"
"$py" -c "$probe"
echo "$want" > "$stamp"
echo "tf2_msgs, tf2, tf2_py, composition_interfaces and tf2_ros built into $venv" >&2
