#!/usr/bin/env bash
# Set up (idempotent), then run the main job end to end on synthesized data:
# synthesize a field trial (ROS 2 bag + truth) -> contact sheet -> backward fit (PSO and CMA-ES) -> report.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
cd "$here"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
exec .venv/bin/uw-sil demo --out-dir "${1:-out}"
