#!/usr/bin/env bash
# A self-contained `flatnet bench` for a machine without Debian 12's packages (another distribution,
# a lent machine): this build's bench command, the shared libraries it loads (ldd's closure, without
# glibc, libstdc++ and libgcc_s, which the other machine's newer ones replace), and the data it reads
# (configs, the reference camera, the golden scenes).
#   scripts/bench_bundle.sh OUT_DIR        (after scripts/build.sh; writes OUT_DIR/flatnet-bench.tar.xz)
# There:  tar xf flatnet-bench.tar.xz && flatnet-bench/run.sh --rows peak,infer_paper --threads 2
# The bench binary reads PNG through libpng instead of OpenImageIO (scripts/bundle/png_io.inc), whose
# plugins would bring ~200 more libraries; everything else is the build's own code. ~130 MB.
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(realpath -m "${1:?usage: scripts/bench_bundle.sh OUT_DIR}")
build=build
[ -f "$build/libflatnet_bench.a" ] && [ -f "$build/CMakeFiles/flatnet.dir/src/cli/bench.cpp.o" ] ||
  { echo "bench_bundle: build first (scripts/build.sh)" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
stage=$work/flatnet-bench
mkdir -p "$stage/bin" "$stage/lib" "$stage/share/models" "$stage/share/tests/data" "$out"

# io/image.cpp with its OpenImageIO section replaced by scripts/bundle/png_io.inc.
python3 - src/io/image.cpp scripts/bundle/png_io.inc "$work/image_png.cpp" <<'PY'
import sys
src, inc, dst = sys.argv[1:]
text = open(src).read()
start, end = text.index("// An image file read once"), text.index("torch::Tensor resize(")
head = text[:start].replace("#include <OpenImageIO/filesystem.h>\n#include <OpenImageIO/imageio.h>\n", "#include <png.h>\n")
open(dst, "w").write(head + open(inc).read() + text[end:])
PY
flags="-std=c++17 -O3 -DNDEBUG -pthread -D_GLIBCXX_USE_CXX11_ABI=1 -DUSE_C10D_GLOO -DUSE_DISTRIBUTED -DUSE_RPC -DUSE_TENSORPIPE"
incs="-I$build/layers/io -I$build/layers/core -isystem /usr/include/torch/csrc/api/include -isystem /usr/include/opencv4"
g++ $flags $incs -c "$work/image_png.cpp" -o "$work/image_png.o"
g++ $flags -I$build/layers/core -c scripts/bundle/bench_main.cpp -o "$work/bench_main.o"
cp "$build/libflatnet_io.a" "$work/io.a"
ar d "$work/io.a" image.cpp.o
ar r "$work/io.a" "$work/image_png.o"
L=/usr/lib/x86_64-linux-gnu
g++ -o "$stage/bin/flatnet-bench" "$work/bench_main.o" "$build/CMakeFiles/flatnet.dir/src/cli/bench.cpp.o" \
  "$build/CMakeFiles/flatnet.dir/src/cli/common.cpp.o" -Wl,--as-needed -Wl,--start-group "$build/libflatnet_core.a" \
  "$work/io.a" "$build"/libflatnet_{optics,nn,recon,eval,train,bench}.a -Wl,--end-group \
  $L/libtorch.so $L/libtorch_cpu.so $L/libc10.so $L/libglog.so $L/libgflags.so -lpthread $L/libmatio.so \
  $L/hdf5/serial/lib/libhdf5.so -lz $L/libyaml-cpp.so $L/libonnx.so $L/libonnx_proto.so $L/libprotobuf.so \
  $L/libdnnl.so $L/libopencv_dnn.so $L/libopencv_imgproc.so $L/libopencv_core.so -lcrypto -lpng16 2>&1 |
  { grep -v "warning" || true; }
ldd "$stage/bin/flatnet-bench" | awk '$3 ~ /^\// {print $3}' |
  grep -vE '/(libc|libm|libdl|librt|libpthread|libstdc\+\+|libgcc_s)\.so' | xargs -r cp -L -t "$stage/lib"
cp -r configs "$stage/share/"
cp -r models/camera "$stage/share/models/"
cp -r tests/data/golden "$stage/share/tests/data/"
cat > "$stage/run.sh" <<'SH'
#!/bin/bash
# flatnet bench from this bundle: ./run.sh --rows peak,infer_paper --threads 2 (--help lists the options)
here=$(dirname "$(realpath "$0")")
LD_LIBRARY_PATH="$here/lib" FLATNET_DATA_DIR="$here/share" exec "$here/bin/flatnet-bench" "$@"
SH
chmod +x "$stage/run.sh"
LD_LIBRARY_PATH="$stage/lib" FLATNET_DATA_DIR="$stage/share" "$stage/bin/flatnet-bench" --help > /dev/null
tar -C "$work" -cf - flatnet-bench | xz -6 -T0 > "$out/flatnet-bench.tar.xz.part"
mv "$out/flatnet-bench.tar.xz.part" "$out/flatnet-bench.tar.xz"
echo "bench_bundle: $out/flatnet-bench.tar.xz ($(du -h "$out/flatnet-bench.tar.xz" | cut -f1), $(ls "$stage/lib" | wc -l) libraries)"
