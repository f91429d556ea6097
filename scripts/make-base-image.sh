#!/bin/sh
# Make a local stand-in for Docker Hub's python:3.11-slim from Debian's own packages, for hosts
# that reach Debian's mirrors but not Docker Hub. Debian bookworm's python3 is 3.11, so the
# project's Dockerfile builds unchanged on top of it.
#
#   scripts/make-base-image.sh [TAG]        (default TAG: python:3.11-slim; needs root)
#
# Environment: DEBIAN_MIRROR (default http://deb.debian.org/debian), SUITE (default bookworm).
set -eu
tag="${1:-python:3.11-slim}"
mirror="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
suite="${SUITE:-bookworm}"
command -v debootstrap >/dev/null || { echo "make-base-image: debootstrap not found (apt-get install debootstrap)" >&2; exit 2; }
root="$(mktemp -d /tmp/recslam-rootfs.XXXXXX)"
trap 'rm -rf "$root"' EXIT
echo "make-base-image: debootstrap $suite from $mirror into $root"
debootstrap --variant=minbase --include=python3,python3-pip,python-is-python3,ca-certificates \
    "$suite" "$root" "$mirror" >"$root.log" 2>&1 || { tail -20 "$root.log" >&2; exit 1; }
rm -f "$root.log"
# As in the official image: pip installs into the system interpreter (no PEP 668 lock), and
# `pip` is on the PATH.
rm -f "$root"/usr/lib/python3*/EXTERNALLY-MANAGED
ln -sf pip3 "$root/usr/bin/pip"
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
tar -C "$root" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' \
    - "$tag" >/dev/null
echo "make-base-image: tagged $tag ($(docker run --rm --network host "$tag" python --version))"
