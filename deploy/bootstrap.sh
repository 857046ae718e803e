#!/usr/bin/env bash
# Set up nprt on a fresh Debian machine: system packages, a virtualenv in .venv and the
# package with its extras. Idempotent: a stamp skips work already done for this pyproject.
#   bash deploy/bootstrap.sh          # runtime only (render, serve, demo)
#   bash deploy/bootstrap.sh --test   # plus test tools, torch (CPU) and Chromium
set -euo pipefail
cd "$(dirname "$0")/.."
want_test=0
[ "${1:-}" = "--test" ] && want_test=1

sudo_if() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

apt_pkgs=(libgomp1)
[ "$want_test" = 1 ] && apt_pkgs+=(chromium)
missing=()
for p in "${apt_pkgs[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if [ "${#missing[@]}" -gt 0 ] && command -v apt-get >/dev/null; then
  echo "bootstrap: apt-get install ${missing[*]}"
  sudo_if apt-get update -qq
  sudo_if env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

py=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$py" -m venv .venv
extras="."
[ "$want_test" = 1 ] && extras=".[test,train]"
stamp=".venv/.nprt-stamp-$(sha256sum pyproject.toml | cut -c1-16)-$want_test"
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  # torch first and pinned: a looser spec pulls gigabytes of CUDA wheels.
  [ "$want_test" = 1 ] && .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -e "$extras"
  touch "$stamp"
fi
echo "bootstrap: ready (.venv)"
