#!/usr/bin/env bash
# Make ./.venv point at a Python 3.11 virtual environment holding exactly requirements.txt, plus the
# message packages the wheels lack (tf2_msgs), generated from interfaces/ by scripts/build_interfaces.sh.
# The environment itself lives under ${DPV_VENV_CACHE:-~/.cache/dpv_sensor}/venv-<hash of
# requirements.txt, interfaces/ and the build script>, so every clone (and every CI run on the same machine)
# reuses one install of the ~6 GB of wheels; a change to any of them gets a fresh environment.
set -euo pipefail
cd "$(dirname "$0")/.."

req=requirements.txt
hash=$(cat "$req" scripts/build_interfaces.sh $(find interfaces -type f | LC_ALL=C sort) | sha256sum | cut -c1-12)
cache=${DPV_VENV_CACHE:-$HOME/.cache/dpv_sensor}
target="$cache/venv-$hash"

if [ -f "$target/.complete" ]; then
  if [ "$(readlink .venv 2>/dev/null)" != "$target" ]; then
    rm -rf .venv && ln -s "$target" .venv
  fi
  exit 0
fi

python=""
for cand in python3.11 python3; do
  if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    python=$(command -v "$cand"); break
  fi
done
if [ -z "$python" ]; then
  echo "ensure_venv: Python 3.11 is required (the ROS 2 Jazzy wheels are built for cp311)" >&2
  exit 1
fi

echo "ensure_venv: creating $target (first run: downloads ~3 GB of wheels)"
mkdir -p "$cache"
rm -rf "$target"
"$python" -m venv "$target"
"$target/bin/pip" install --quiet --upgrade pip
# The ROS wheels and what the message generation needs come first; tf2_msgs is then generated in the background
# while pip installs the rest (torch, open3d, gtsam, ...: most of the download), so the two overlap.
build_reqs=$(mktemp "${TMPDIR:-/tmp}/dpv_build_reqs.XXXXXX")
build_log=$(mktemp "${TMPDIR:-/tmp}/dpv_build_interfaces.XXXXXX")
trap 'rm -f "$build_reqs" "$build_log"' EXIT
grep -E '^(ros-jazzy-|catkin-pkg==|numpy==)' "$req" > "$build_reqs"
"$target/bin/pip" install --quiet -r "$build_reqs"
CMAKE_BUILD_PARALLEL_LEVEL=$(nproc 2>/dev/null || echo 2) scripts/build_interfaces.sh "$target" >"$build_log" 2>&1 &
build_pid=$!
"$target/bin/pip" install --quiet -r "$req" || { kill "$build_pid" 2>/dev/null; wait "$build_pid" 2>/dev/null; exit 1; }
# torch from PyPI drags in triton (~1 GB) which only serves CUDA kernels compiled at run time.
"$target/bin/pip" uninstall --quiet -y triton || true
if ! wait "$build_pid"; then
  cat "$build_log" >&2
  exit 1
fi
cat "$build_log"
touch "$target/.complete"
rm -rf .venv && ln -s "$target" .venv
echo "ensure_venv: ready"
