#!/usr/bin/env bash
# Include hygiene without the precompiled header. Every target reuses one PCH (torch and the
# standard headers), which hides a missing #include. This compiles (syntax only, no PCH):
#   - each header of src/ alone, so every header includes what it uses;
#   - with --sources, every .cpp of src/ and tests/ as well (slow: ~10 s per file with torch).
# Needs a configured build (build/compile_commands.json). Usage: scripts/check_headers.sh [--sources]
set -euo pipefail
cd "$(dirname "$0")/.."
db=build/compile_commands.json
[ -f "$db" ] || { echo "check_headers: no $db (run scripts/build.sh first)" >&2; exit 2; }
# The flags of one library TU, minus the output, the source and the PCH.
flags=$(/usr/bin/python3 - "$db" <<'PY'
import json, shlex, sys
for e in json.load(open(sys.argv[1])):
    if '/src/nn/' in e['file']:
        args = shlex.split(e['command'])[1:]
        out, skip = [], False
        for a in args:
            if skip: skip = False; continue
            if a in ('-o', '-c', '-include', '-MF', '-MT'): skip = True; continue
            if a.startswith('-Winvalid-pch') or a.endswith('.cpp') or a == '-MD': continue
            out.append(a)
        print(' '.join(shlex.quote(a) for a in out)); break
PY
)
files=(src/*/*.hpp)
[ "${1:-}" = "--sources" ] && files+=(src/*/*.cpp tests/*.cpp)
fail=0
check() {  # one file, syntax only; headers through a one-line TU
  local f=$1 out
  if [[ $f == *.hpp ]]; then
    out=$(echo "#include \"${f#src/}\"" | eval g++ $flags -Isrc -Itests -fsyntax-only -x c++ - 2>&1) || { echo "FAIL $f"; echo "$out" | head -5; return 1; }
  else
    out=$(eval g++ $flags -Isrc -Itests -DFLATNET_TEST_DATA=\\\"t\\\" -DFLATNET_SHARED_DIR=\\\"s\\\" -DFLATNET_BINARY=\\\"b\\\" -DFLATNET_BUILD_DIR=\\\"d\\\" -fsyntax-only "$f" 2>&1) || { echo "FAIL $f"; echo "$out" | head -5; return 1; }
  fi
}
export -f check; export flags
printf '%s\n' "${files[@]}" | xargs -P "${FLATNET_JOBS:-2}" -I{} bash -c 'check {}' || fail=1
[ $fail = 0 ] && echo "check_headers: ${#files[@]} files compile without the precompiled header" || { echo "check_headers: failures above"; exit 1; }
