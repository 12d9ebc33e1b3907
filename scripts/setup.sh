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
# OpenVDB's Python module (pyopenvdb), for density grids in .vdb files (optional: without
# it a .vdb is a one-line error; .npy and .vol grids need nothing)
if ! installed python3-openvdb; then
  echo "setup: installing python3-openvdb from Debian (.vdb density grids)" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-openvdb >/dev/null \
    || echo "setup: python3-openvdb could not be installed; .vdb files will not be read" >&2
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
# a venv of another Python build (pyenv's) does not see Debian's dist-packages: link the
# pyopenvdb module alone into it (the rest of dist-packages, NumPy 1.x among it, would
# shadow the venv's own packages); it must be built for the venv's Python version
if ! .venv/bin/python -c "import pyopenvdb" >/dev/null 2>&1; then
  ext=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_config_var('EXT_SUFFIX'))")
  site=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['platlib'])")
  so="/usr/lib/python3/dist-packages/pyopenvdb$ext"
  if [ -f "$so" ]; then
    ln -sf "$so" "$site/"
  elif installed python3-openvdb; then
    echo "setup: python3-openvdb has no pyopenvdb$ext for the venv's Python; .vdb files will not be read" >&2
  fi
fi
# byte-compile the package (pip does it for a regular install; an editable one, or a
# shell with PYTHONDONTWRITEBYTECODE set, would otherwise compile every module in every
# process: ~0.2 s of each command's start-up). Up-to-date files are skipped.
.venv/bin/python -m compileall -q clscatter >/dev/null
