#!/usr/bin/env bash
# Runs gcode-bench with Python's pygcode as a second independent parser:
# installs pygcode into a throw-away virtualenv, then passes its python to the
# bench. Usage (from anywhere): gcode/benches/with-pygcode.sh [bench options]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${PYGCODE_VENV:-${TMPDIR:-/tmp}/fresa-pygcode-venv}"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/python" -c 'import pygcode' 2>/dev/null || "$venv/bin/pip" install -q pygcode
cd "$here/../.."
CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-/work/target-gcode}" \
    cargo bench -p fresa-gcode --bench gcode-bench -- --python "$venv/bin/python" "$@"
