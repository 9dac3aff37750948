#!/usr/bin/env bash
# Include hygiene without the precompiled header. Every target reuses one PCH (torch and the
# standard headers), which hides a missing #include. This compiles (syntax only, no PCH):
#   - each header of src/ alone, so every header includes what it uses;
#   - with --sources, every .cpp of src/ and tests/ too, each with its own flags (slow: ~10 s a file).
# Needs a configured build (build/compile_commands.json). Usage: scripts/check_headers.sh [--sources]
set -euo pipefail
cd "$(dirname "$0")/.."
db=build/compile_commands.json
[ -f "$db" ] || { echo "check_headers: no $db (run scripts/build.sh first)" >&2; exit 2; }
list=$(mktemp)
trap 'rm -f "$list"' EXIT
# One line per file: the file, a tab, its compile flags minus the output, the source and the PCH.
# A header gets the flags of an nn/ source plus src/ (any layer's headers); a source, its own.
/usr/bin/python3 - "$db" "${1:-}" > "$list" <<'PY'
import glob, json, os, shlex, sys
entries = json.load(open(sys.argv[1]))
def flags(e):
    out, skip = [], False
    for a in shlex.split(e['command'])[1:]:
        if skip: skip = False; continue
        if a in ('-o', '-c', '-include', '-MF', '-MT'): skip = True; continue
        if a == '-MD' or a == e['file'] or a.endswith('.cpp'): continue
        out.append(a)
    return ' '.join(shlex.quote(a) for a in out)
by_file = {os.path.relpath(e['file']): e for e in entries}
# A unity build (FLATNET_UNITY_BUILD) compiles Unity/unity_N_cxx.cxx, which #includes a layer's
# sources: each of them gets that entry's flags.
for e in entries:
    if '/Unity/' in e['file']:
        for line in open(e['file']):
            if line.startswith('#include "') and line.rstrip().endswith('.cpp"'):
                by_file[os.path.relpath(line.strip()[len('#include "'):-1])] = e
header_flags = next(flags(e) for f, e in by_file.items() if f.startswith('src/nn/')) + ' -Isrc'
for h in sorted(glob.glob('src/*/*.hpp')):
    print(h + '\t' + header_flags)
if sys.argv[2] == '--sources':
    for f in sorted(by_file):
        if (f.startswith('src/') or f.startswith('tests/')) and f.endswith('.cpp') and f != 'src/core/pch.cpp':
            print(f + '\t' + flags(by_file[f]))
PY
check() {  # "file<TAB>flags": syntax only; a header through a one-line TU
  local f=${1%%$'\t'*} flags=${1#*$'\t'} out
  if [[ $f == *.hpp ]]; then
    out=$(echo "#include \"${f#src/}\"" | eval g++ "$flags" -fsyntax-only -x c++ - 2>&1) || { echo "FAIL $f"; echo "$out" | head -5; return 1; }
  else
    out=$(eval g++ "$flags" -fsyntax-only "$f" 2>&1) || { echo "FAIL $f"; echo "$out" | head -5; return 1; }
  fi
}
export -f check
count=$(wc -l < "$list")
if tr '\n' '\0' < "$list" | xargs -0 -P "${FLATNET_JOBS:-2}" -I{} bash -c 'check "$1"' _ {}; then
  echo "check_headers: $count files compile without the precompiled header"
else
  echo "check_headers: failures above"; exit 1
fi
