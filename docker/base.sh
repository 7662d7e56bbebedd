#!/usr/bin/env bash
# Build a local Debian bookworm base image (python3 + venv + CA certificates) with mmdebstrap and
# import it into podman (or docker) as $BASE_TAG. For machines where no registry serves base images;
# elsewhere the Dockerfiles' default BASE_IMAGE (python:3.11-slim) is fine.
#   docker/base.sh [TAG]      (env: ENGINE=podman|docker, SUITE=bookworm, MIRROR=http://deb.debian.org/debian)
set -euo pipefail
BASE_TAG="${1:-triscan-base:bookworm}"
ENGINE="${ENGINE:-podman}"
SUITE="${SUITE:-bookworm}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"

if [[ "${FORCE:-0}" != 1 ]] && "$ENGINE" image exists "$BASE_TAG" 2>/dev/null; then
    echo "base image $BASE_TAG exists (FORCE=1 to rebuild)"
    exit 0
fi
tarball="$(mktemp --suffix=.tar)"
trap 'rm -f "$tarball"' EXIT
# minbase = Essential + apt only; python3-venv brings ensurepip (pip inside the images' venvs).
nice -n 19 mmdebstrap --variant=minbase --mode=root --format=tar \
    --include=python3,python3-venv,ca-certificates \
    --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/doc/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*' \
    "$SUITE" "$tarball" "$MIRROR"
"$ENGINE" import --change 'CMD ["python3"]' --change 'ENV LANG=C.UTF-8' "$tarball" "$BASE_TAG"
"$ENGINE" image ls "$BASE_TAG"
