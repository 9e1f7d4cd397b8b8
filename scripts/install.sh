#!/usr/bin/env bash
# Create .venv (Python 3.11) and install curlnav into it, CPU torch first so that the
# project's torch range is already met and pip does not fetch a multi-GB CUDA build.
# Safe to re-run: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
python -c 'import sys; assert sys.version_info[:2] == (3, 11), f"curlnav needs Python 3.11, found {sys.version.split()[0]}"'
if ! python -c 'import torch' >/dev/null 2>&1; then
  echo "[install] torch (CPU build 2.13.0)"
  pip install --quiet --disable-pip-version-check torch==2.13.0 \
    || pip install --quiet --disable-pip-version-check torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
fi
echo "[install] curlnav and its dependencies"
pip install --quiet --disable-pip-version-check -e ".[test]"
