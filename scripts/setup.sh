#!/usr/bin/env bash
# One-time (idempotent) set-up on a Debian machine: PoCL, the OpenCL CPU device, from
# Debian's pocl-opencl-icd, and clscatter with its test dependencies in ./.venv (which
# reuses already-installed system packages). Prints nothing when all is in place.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
installed() {  # dpkg -s also succeeds for removed packages that left config files
  [ "$(dpkg-query -W -f='${Status}' "$1" 2>/dev/null)" = "install ok installed" ]
}
if ! installed pocl-opencl-icd || ! installed ocl-icd-libopencl1; then
  echo "setup: installing PoCL (pocl-opencl-icd) from Debian" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq pocl-opencl-icd ocl-icd-libopencl1 >/dev/null
fi
# Oclgrind, a second OpenCL implementation (a strict simulator reporting invalid accesses
# and data races), for the test that runs every method under it
if ! installed oclgrind; then
  echo "setup: installing oclgrind from Debian (every method is tested under it)" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq oclgrind >/dev/null \
    || echo "setup: oclgrind could not be installed; its test will be skipped" >&2
fi
# headless Chromium for the browser test of `clscatter serve` (Playwright drives Debian's
# chromium; Playwright's own browser download is not used)
if ! command -v chromium >/dev/null 2>&1; then
  echo "setup: installing chromium from Debian (browser test of clscatter serve)" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null \
    || echo "setup: chromium could not be installed; the browser test will fail" >&2
fi
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  if ! $PY -m venv --system-site-packages .venv 2>/dev/null; then
    echo "setup: installing python3-venv from Debian" >&2
    rm -rf .venv
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv >/dev/null
    $PY -m venv --system-site-packages .venv
  fi
fi
if ! .venv/bin/python -c "import clscatter, pyopencl, trimesh, skimage, scipy, tqdm, OpenEXR, threadpoolctl, pytest, distributed, starlette, uvicorn, websockets, httpx, playwright" 2>/dev/null \
   || [ pyproject.toml -nt .venv/.installed ]; then
  echo "setup: installing clscatter and its dependencies into .venv" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
  touch .venv/.installed
fi
# byte-compile the package (pip does it for a regular install; an editable one, or a
# shell with PYTHONDONTWRITEBYTECODE set, would otherwise compile every module in every
# process: ~0.2 s of each command's start-up). Up-to-date files are skipped.
.venv/bin/python -m compileall -q clscatter >/dev/null
