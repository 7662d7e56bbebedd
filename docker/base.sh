#!/usr/bin/env bash
# Build a local Debian bookworm base image (python3 + venv + CA certificates) with mmdebstrap and
# import it into podman (or docker) as $BASE_TAG. For machines where no registry serves base images;
# elsewhere the Dockerfiles' default BASE_IMAGE (python:3.11-slim) is fine.
#   docker/base.sh [TAG]      (env: ENGINE=podman|docker, SUITE=bookworm, MIRROR=http://deb.debian.org/debian,
#                              ARCH=<Debian arch, default this machine's>)
# ARCH=arm64 on an x86-64 machine builds an arm64 root file system: mmdebstrap runs its maintainer
# scripts under qemu-user-static (binfmt_misc must be registered; docker/check_arm64.sh does it).
set -euo pipefail
BASE_TAG="${1:-triscan-base:bookworm}"
ENGINE="${ENGINE:-podman}"
SUITE="${SUITE:-bookworm}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"
ARCH="${ARCH:-$(dpkg --print-architecture)}"

if [[ "${FORCE:-0}" != 1 ]] && "$ENGINE" image exists "$BASE_TAG" 2>/dev/null; then
    echo "base image $BASE_TAG exists (FORCE=1 to rebuild)"
    exit 0
fi
tarball="$(mktemp --suffix=.tar)"
trap 'rm -f "$tarball"' EXIT
# minbase = Essential + apt only; python3-venv brings ensurepip (pip inside the images' venvs).
# shellcheck disable=SC2016  # "$1" is the hook's argument, expanded by mmdebstrap's shell
nice -n 19 mmdebstrap --variant=minbase --mode=root --format=tar --architectures="$ARCH" \
    --include=python3,python3-venv,ca-certificates \
    --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/doc/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*' \
    "$SUITE" "$tarball" "$MIRROR"
"$ENGINE" import --arch "$ARCH" --change 'CMD ["python3"]' --change 'ENV LANG=C.UTF-8' "$tarball" "$BASE_TAG"
"$ENGINE" image ls "$BASE_TAG"
