#!/usr/bin/env bash
# Generate and install the ROS message packages that the PyPI ROS 2 wheels lack (tf2_msgs: /tf and /tf_static)
# into a Python environment that is also a ROS prefix: `scripts/build_interfaces.sh <venv>`.
# The venv must hold requirements.txt (rosidl generators, ament_cmake). Python modules land in its site-packages,
# libraries in <venv>/lib (on the library path the ROS wheels set up), the ament index in <venv>/share, so the
# node, the tests and `colcon build` + `ros2 run` in that venv all find the messages with no extra variables.
# Needs cmake >= 3.16 and a C/C++ compiler; ninja is used when present. Takes ~20 s.
set -euo pipefail
cd "$(dirname "$0")/.."

prefix=$(cd "${1:?usage: build_interfaces.sh <venv prefix>}" && pwd)
python="$prefix/bin/python"
for tool in cmake cc c++; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    echo "build_interfaces: '$tool' is required to generate the tf2_msgs messages (install cmake and gcc/g++)" >&2
    exit 1
  fi
done
generator=()
if command -v ninja >/dev/null 2>&1; then generator=(-G Ninja); fi

build=$(mktemp -d "${TMPDIR:-/tmp}/dpv_interfaces.XXXXXX")
trap 'rm -rf "$build"' EXIT
for pkg in interfaces/*/; do
  name=$(basename "$pkg")
  echo "build_interfaces: generating $name into $prefix"
  PATH="$prefix/bin:$PATH" AMENT_PREFIX_PATH="$prefix" CMAKE_PREFIX_PATH="$prefix" \
    cmake -S "$pkg" -B "$build/$name" "${generator[@]}" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
      -DCMAKE_INSTALL_PREFIX="$prefix" -DPython3_EXECUTABLE="$python" >"$build/$name.log" 2>&1 \
    && PATH="$prefix/bin:$PATH" cmake --build "$build/$name" >>"$build/$name.log" 2>&1 \
    && cmake --install "$build/$name" >>"$build/$name.log" 2>&1 \
    || { cat "$build/$name.log" >&2; echo "build_interfaces: $name failed (log above)" >&2; exit 1; }
done
"$python" -c 'from tf2_msgs.msg import TFMessage; TFMessage()' \
  || { echo "build_interfaces: tf2_msgs was built but does not import in $python" >&2; exit 1; }
