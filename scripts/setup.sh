#!/usr/bin/env bash
# Idempotent set-up: a virtual environment in .venv with everything capssim needs.
#  - torch==2.13.0 first (a CPU build is cached on the project machines; a bare 'torch' pulls GBs)
#  - the project with its test (pytest, ruff) and docs (MkDocs) extras, editable
#  - libllvm19 for Mitsuba's LLVM variants where apt can install it; otherwise capssim falls back
#    to the scalar variants with a one-line notice.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}
stamp="$VENV/.capssim-installed"
want="$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
# pip's and setuptools' notes (the editable-install advisory, the machine's pip mirror settings) go to a
# log that is printed only when an install fails, so a successful set-up prints no warnings.
log="$(mktemp "${TMPDIR:-/tmp}/capssim-setup.XXXXXX")"
quiet_pip() {
  if ! "$VENV/bin/python" -m pip install -q "$@" >"$log" 2>&1; then
    cat "$log" >&2
    echo "capssim setup: 'pip install $*' failed (log above)" >&2
    exit 1
  fi
}
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
quiet_pip "torch==2.13.0"
quiet_pip -e ".[test,docs]"
rm -f "$log"

if ! ls /usr/lib/*/libLLVM.so.19* /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1; then
  SUDO=""
  if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO="sudo -n"; fi
  if [ "$(id -u)" = "0" ] || [ -n "$SUDO" ]; then
    export DEBIAN_FRONTEND=noninteractive
    ($SUDO apt-get install -y -q libllvm19 >/dev/null 2>&1 \
      || ($SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q libllvm19 >/dev/null 2>&1)) \
      || echo "capssim setup: libllvm19 could not be installed; rendering will use Mitsuba's scalar variants (slower)."
  else
    echo "capssim setup: no root to install libllvm19; rendering will use Mitsuba's scalar variants (slower)."
  fi
fi
echo "$want" > "$stamp"
echo "capssim setup: ready in $VENV"
