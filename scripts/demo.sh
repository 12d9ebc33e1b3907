#!/usr/bin/env bash
# Set up (if needed) and render the built-in demo scene to clscatter-demo.png.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/clscatter render -o "${1:-clscatter-demo.png}"
