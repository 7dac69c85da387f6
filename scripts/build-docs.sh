#!/usr/bin/env bash
# Strict build of the documentation site into site/ (mkdocs.yml): a broken link, anchor, nav entry or
# API cross-reference fails it. Needs the docs extra: .venv/bin/pip install -e ".[docs]".
# Needs neither ../shared nor a GPU.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
if ! "$VENV/bin/python" -c "import mkdocs, mkdocstrings, mkdocs_gen_files, mkdocs_literate_nav, material" 2>/dev/null; then
  echo "build-docs: the docs tools are missing; install them with: $VENV/bin/pip install -e \".[docs]\"" >&2
  exit 2
fi
# Material and the MkDocs plugins print banners about MkDocs 2.0 on every build; they change nothing here.
export NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true
exec "$VENV/bin/python" -m mkdocs build --strict --clean --site-dir site "$@"
