#!/usr/bin/env bash
# Make sure a Docker engine runs here (for the container smoke test). On a Debian machine with
# only the Docker client (as ours), install Debian's engine, Compose 1.29 and debootstrap, and
# start dockerd in the background. Exits non-zero when no engine can be had.
set -euo pipefail
if docker info >/dev/null 2>&1; then
  echo "[docker] engine running"; exit 0
fi
if ! command -v dockerd >/dev/null 2>&1 || ! command -v docker-compose >/dev/null 2>&1 || ! command -v debootstrap >/dev/null 2>&1; then
  if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "[docker] no engine and no way to install one (needs root and apt-get)"; exit 1
  fi
  echo "[docker] installing docker.io, docker-compose, debootstrap"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null
  apt-get install -y -qq docker.io docker-compose debootstrap >/dev/null
fi
echo "[docker] starting dockerd"
(nohup dockerd >/tmp/dockerd.log 2>&1 &)
for _ in $(seq 1 60); do
  if docker info >/dev/null 2>&1; then echo "[docker] engine running"; exit 0; fi
  sleep 1
done
echo "[docker] dockerd did not start; see /tmp/dockerd.log"; tail -n 20 /tmp/dockerd.log; exit 1
