#!/usr/bin/env bash
# Installs every Debian package flatnet needs. Idempotent and non-interactive:
# packages already present are skipped, so a second run costs a few seconds.
#
# Traps this script takes care of (README "Quick start"):
#  - libaravis-dev forgets libusb-1.0-0-dev, which its pkg-config file requires.
#  - libgloo-dev is needed for LibTorch's c10d (distributed training).
#  - libopenblas0-openmp: without it LibTorch falls back to reference BLAS (2-60x slower).
#  - xvfb + xauth: the capture tests show scenes in a real (virtual) window; iproute2 and
#    util-linux's unshare run Aravis's GigE Vision simulator in a loopback-only namespace.
#  - python3-skimage (its data folder) provides the photographs `flatnet demo` uses on a fresh machine.
#  - ONNX Runtime (optional, for the ONNX deployment test): the npm registry's onnxruntime-node holds
#    the CPU runtime; installed with --ignore-scripts (its install script only fetches GPU parts) under
#    ~/.cache/flatnet/onnxruntime-node-VERSION, where CMakeLists.txt's FLATNET_ORT_DIR looks.
#  - chromium (optional): the test of `flatnet report`'s report.html loads the page headless and
#    takes a screenshot; without it that test shows as skipped.
#  - python3-torch is optional: only reference comparisons in scripts/ and a few tests use it;
#    FLATNET_SKIP_OPTIONAL=1 leaves the optional packages out (those tests then show as skipped).
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config
  libtorch-dev libopenblas0-openmp libgloo-dev
  libopencv-dev libopenimageio-dev openimageio-tools
  libaravis-dev aravis-tools libusb-1.0-0-dev xvfb xauth iproute2
  libmatio-dev libhdf5-dev libcxxopts-dev catch2 libyaml-cpp-dev nlohmann-json3-dev
  libonnx-dev libprotobuf-dev zlib1g-dev libdnnl-dev libssl-dev
  python3-skimage
)
optional=(python3-torch clang-format chromium)
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then optional+=(nodejs npm); fi
ort_version=1.20.1
ort_dir="${FLATNET_ORT_DIR:-$HOME/.cache/flatnet/onnxruntime-node-$ort_version}"

install_onnxruntime() {
  [ -n "${FLATNET_SKIP_OPTIONAL:-}" ] && return 0
  [ -f "$ort_dir/node_modules/onnxruntime-node/package.json" ] && return 0
  command -v npm >/dev/null || { echo "setup: no npm; ONNX Runtime not installed (its test will be skipped)"; return 0; }
  echo "setup: installing onnxruntime-node@$ort_version into $ort_dir"
  mkdir -p "$ort_dir"
  npm install --prefix "$ort_dir" --ignore-scripts --no-audit --no-fund --loglevel=error \
    "onnxruntime-node@$ort_version" >/dev/null ||
    echo "setup: onnxruntime-node not installed (its test will be skipped)"
}
if [ -n "${FLATNET_SKIP_OPTIONAL:-}" ]; then optional=(); fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

missing=()
for p in "${packages[@]}" "${optional[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "setup: all ${#packages[@]} required packages present"
  install_onnxruntime
  exit 0
fi

echo "setup: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
# Required packages must install; optional ones may be absent from a mirror.
req_missing=()
for p in "${missing[@]}"; do
  case " ${optional[*]} " in *" $p "*) ;; *) req_missing+=("$p") ;; esac
done
if [ ${#req_missing[@]} -gt 0 ]; then
  $SUDO apt-get install -y -qq --no-install-recommends "${req_missing[@]}"
fi
for p in "${optional[@]}"; do
  $SUDO apt-get install -y -qq --no-install-recommends "$p" || echo "setup: optional $p not installed"
done
install_onnxruntime
echo "setup: done"
