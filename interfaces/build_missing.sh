#!/usr/bin/env bash
# Builds the message packages under interfaces/ that the venv cannot import (no pip wheel exists for
# them, e.g. tf2_msgs) with the ament_cmake and rosidl wheels of requirements.txt, gcc and cmake, and
# installs them into the venv's prefix. A package that already imports (a real ROS 2 install, or an
# earlier build) is left alone.  Usage: interfaces/build_missing.sh VENV
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="$(cd "${1:?usage: build_missing.sh VENV}" && pwd)"
py="$venv/bin/python"

# what a package defines (msg, srv, action), as the Python imports that must work once it is built
imports() { local kinds=(); for kind in msg srv action; do [ -d "$here/$1/$kind" ] && kinds+=("import $1.$kind"); done
            (IFS=';'; echo "${kinds[*]}"); }
missing=()
for pkg in "$here"/*/; do
  name="$(basename "$pkg")"
  "$py" -c "$(imports "$name")" >/dev/null 2>&1 || missing+=("$name")
done
[ ${#missing[@]} -eq 0 ] && exit 0
for tool in cmake gcc g++; do
  command -v "$tool" >/dev/null || { echo "interfaces: $tool is needed to build ${missing[*]}" >&2; exit 1; }
done

build="$(mktemp -d)"; log="$build/log"
trap 'rm -rf "$build"' EXIT

# The message wheels' exported CMake targets name the include directories of the machine that built
# them (/opt/python/cp3XX-cp3XX/...). The build sees the venv through an overlay prefix in which those
# packages' share/ folders are copies pointing at this venv's Python and numpy headers; the venv's own
# files stay as pip installed them.
inc="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
npinc="$("$py" -c 'import numpy; print(numpy.get_include())')"
overlay="$build/prefix"
mkdir -p "$overlay/share"
for dir in lib include bin; do [ -e "$venv/$dir" ] && ln -s "$venv/$dir" "$overlay/$dir"; done
{ grep -rlE '/opt/python/cp3[0-9]+-cp3[0-9]+' "$venv/share" --include='*.cmake' 2>/dev/null || true; } \
  | sed -E "s#^$venv/share/([^/]+)/.*#\1#" | sort -u | while read -r pkg; do
  cp -r "$venv/share/$pkg" "$overlay/share/$pkg"
  find "$overlay/share/$pkg" -name '*.cmake' -exec sed -i -E \
    "s#/opt/python/cp3[0-9]+-cp3[0-9]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#$npinc#g;
     s#/opt/python/cp3[0-9]+-cp3[0-9]+/include/python3\.[0-9]+#$inc#g" {} +
done
for name in "${missing[@]}"; do
  echo "interfaces: building $name into $venv (no wheel for it)"
  if ! (export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$overlay:$venv" CMAKE_PREFIX_PATH="$overlay:$venv"
        cmake -S "$here/$name" -B "$build/$name" -DCMAKE_INSTALL_PREFIX="$venv" -DPython3_EXECUTABLE="$py" \
          -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
        && cmake --build "$build/$name" -j "$(nproc)" && cmake --install "$build/$name") >"$log" 2>&1; then
    echo "interfaces: building $name failed:" >&2; tail -n 20 "$log" >&2; exit 1
  fi
  "$py" -c "$(imports "$name")" || { echo "interfaces: $name built but does not import" >&2; exit 1; }
done
