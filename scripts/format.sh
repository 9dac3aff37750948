#!/usr/bin/env bash
# Formats the C++ sources with .clang-format (Debian's clang-format 14).
#   scripts/format.sh           rewrite src/ and tests/ in place
#   scripts/format.sh --check   list the files that differ from the style; exit 1 if any
set -euo pipefail
cd "$(dirname "$0")/.."
command -v clang-format >/dev/null || { echo "format.sh: clang-format is missing (apt install clang-format)" >&2; exit 2; }
mapfile -t files < <(git ls-files 'src/*.cpp' 'src/*.hpp' 'tests/*.cpp' 'tests/*.hpp')
if [ "${1:-}" = "--check" ]; then
  status=0
  for f in "${files[@]}"; do
    clang-format --dry-run -Werror "$f" >/dev/null 2>&1 || { echo "$f"; status=1; }
  done
  exit $status
fi
clang-format -i "${files[@]}"
