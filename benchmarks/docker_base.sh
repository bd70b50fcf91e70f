#!/usr/bin/env bash
# Build a stand-in for the Dockerfile's base image where the registry cannot be reached:
#
#   bash benchmarks/docker_base.sh [ROOTFS_DIR]
#
# debootstrap makes a Debian bookworm root file system from the machine's own apt mirror,
# `docker import` turns it into an image, and a small build adds Debian's Python 3.11 as a
# venv in /usr/local (so `python` and `pip` are where python:3.11-slim has them). The
# result is tagged with the Dockerfile's FROM name, so `docker build --network host .`
# then runs unchanged. Certificates that this machine's own trust store adds
# (/usr/local/share/ca-certificates, e.g. an egress proxy's) go into the stand-in, and pip
# is pointed at the system bundle, so the build reaches the package index as the host does.
# Needs root, docker (dockerd running) and debootstrap. Takes 5-10 minutes.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
rootfs="${1:-/tmp/geoidspline-rootfs}"
base="$(awk 'toupper($1) == "FROM" {print $2; exit}' "$repo/Dockerfile")"
mirror="$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/*.sources 2>/dev/null || true)"
mirror="${mirror:-http://deb.debian.org/debian}"

if [ ! -x "$rootfs/usr/bin/apt-get" ]; then
  debootstrap --variant=minbase bookworm "$rootfs" "$mirror"
fi
tar -C "$rootfs" -c . | docker import - geoidspline-bookworm-rootfs

ctx="$(mktemp -d)"
trap 'rm -rf "$ctx"' EXIT
mkdir -p "$ctx/certs"
cp /usr/local/share/ca-certificates/*.crt "$ctx/certs/" 2>/dev/null || true
cat >"$ctx/Dockerfile" <<'DOCKER'
FROM geoidspline-bookworm-rootfs
COPY certs/ /usr/local/share/ca-certificates/
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
 && update-ca-certificates \
 && rm -rf /var/lib/apt/lists/* \
 && python3 -m venv /usr/local \
 && /usr/local/bin/pip --version
ENV PATH=/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin \
    LANG=C.UTF-8 \
    PIP_CERT=/etc/ssl/certs/ca-certificates.crt
CMD ["python3"]
DOCKER
docker build --network host -t "$base" "$ctx"
echo "stand-in for $base built from $rootfs ($mirror)"
