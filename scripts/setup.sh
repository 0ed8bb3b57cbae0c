#!/usr/bin/env bash
# Set up everything a fresh machine needs: Debian packages, .venv, pinned Python packages.
# Idempotent: a second run only checks. Used by `make demo` and `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# open3d needs libusb-1.0 at import time (ImportError: libusb-1.0.so.0 otherwise).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    echo "[setup] installing Debian package libusb-1.0-0 (needed by open3d)"
    SUDO=""
    if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
    $SUDO apt-get update -q >/dev/null
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup] creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi

STAMP="$VENV/.govnesf-installed"
if [ ! -f "$STAMP" ] || [ pyproject.toml -nt "$STAMP" ] || [ setup.py -nt "$STAMP" ] \
        || [ constraints.txt -nt "$STAMP" ] || [ govnesf/__init__.py -nt "$STAMP" ]; then
    echo "[setup] installing pinned packages into $VENV (about a minute on a cold machine)"
    start=$(date +%s)
    # every extra (docs/getting-started/install.md): the demo needs [sim], the tests cover [rerun], [import], [clip]
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check -c constraints.txt -e '.[all,dev]'
    echo "[setup] installed in $(( $(date +%s) - start )) s"
    touch "$STAMP"
fi
