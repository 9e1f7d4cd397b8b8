#!/usr/bin/env bash
# Download every wheel the image needs into wheelhouse/ (for engines without registry access).
# Uses this machine's pip configuration, so the CPU build of torch is taken where it lies on disk.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -m pip download --quiet --disable-pip-version-check --only-binary=:all: \
  --python-version 3.11 --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 \
  --platform manylinux_2_17_x86_64 --platform any \
  -d wheelhouse -r docker/requirements.txt
ls wheelhouse/*.whl | wc -l | xargs echo "[wheelhouse] wheels:"
