#!/usr/bin/env bash
# Make a local Debian bookworm base image with Python 3.11 (no registry needed): debootstrap a
# minimal system from the Debian mirror apt uses here and import it as IMAGE (default
# curlnav-base:bookworm). Needs root, debootstrap and a running Docker engine.
set -euo pipefail
IMAGE=${1:-curlnav-base:bookworm}
if docker image inspect "$IMAGE" >/dev/null 2>&1; then
  echo "[base] $IMAGE exists"; exit 0
fi
MIRROR=${DEBIAN_MIRROR:-$( (grep -h '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{print $2}'; \
  grep -hE '^deb ' /etc/apt/sources.list 2>/dev/null | awk '{print $2}') | grep -m1 debian || true)}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
ROOT=$(mktemp -d)
trap 'rm -rf "$ROOT"' EXIT
echo "[base] debootstrap bookworm from $MIRROR"
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates,libstdc++6,libgomp1 \
  bookworm "$ROOT" "$MIRROR" >/dev/null
tar -C "$ROOT" -c . | docker import - "$IMAGE" >/dev/null
echo "[base] imported $IMAGE"
