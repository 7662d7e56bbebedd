#!/bin/sh
# Build-time only: install triscan's base requirements plus the extras named ($@), read from
# /tmp/pyproject.toml, into /opt/venv; then drop pip, setuptools and bytecode caches (KEEP_PIP=1 keeps
# them for a later call). `pip-install.sh --project DIR` then installs triscan itself from DIR, a copy
# of the repository's packages, without dependencies: the wheel `pip install .` builds.
# Uses the CA bundle from the optional build secret `ca` and $PIP_INDEX_URL when they are given.
set -eu
PROJECT=
if [ "${1:-}" = "--project" ]; then PROJECT=$2; shift 2; fi
python3 - "$@" > /tmp/requirements.txt <<'PY'
import sys, tomllib
project = tomllib.load(open("/tmp/pyproject.toml", "rb"))["project"]
extras = [r for extra in sys.argv[1:] for r in project["optional-dependencies"][extra]]
print("\n".join(project["dependencies"] + extras))
PY
echo "installing: $(tr '\n' ' ' < /tmp/requirements.txt)"
if [ -s /run/secrets/ca ]; then export PIP_CERT=/run/secrets/ca; fi
if [ -n "${PIP_INDEX_URL:-}" ]; then export PIP_INDEX_URL; else unset PIP_INDEX_URL; fi
/opt/venv/bin/pip install --no-cache-dir --disable-pip-version-check -r /tmp/requirements.txt
if [ -n "$PROJECT" ]; then
    /opt/venv/bin/pip install --no-cache-dir --disable-pip-version-check --no-deps "$PROJECT"
    rm -rf "$PROJECT"
fi
[ "${KEEP_PIP:-0}" = 1 ] || /opt/venv/bin/pip uninstall --disable-pip-version-check -y pip setuptools >/dev/null 2>&1 || true
find /opt/venv -name __pycache__ -prune -exec rm -rf {} +
rm -f /tmp/requirements.txt
