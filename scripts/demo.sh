#!/usr/bin/env bash
# The main job on the bundled sample (a real T1 head MRI, tests/data/): called by `make demo`.
# Writes everything under $DEMO (default demo-output/).
set -euo pipefail
cd "$(dirname "$0")/.."
DEMO=${DEMO:-demo-output}
BIN=${BIN:-.venv/bin}
export PATH="$PWD/$BIN:$PATH"
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
mkdir -p "$DEMO"
SCAN=tests/data/mri_t1_head_coronal_2x2x3mm.nrrd
step() { printf '\n== %s\n' "$*"; }

step "info: the bundled scan"
volwarp info "$SCAN"

step "convert: NRRD -> NIfTI -> TIFF -> NRRD, geometry kept"
volwarp convert "$SCAN" -o "$DEMO/head.nii.gz"
volwarp convert "$DEMO/head.nii.gz" -o "$DEMO/head.tif"
volwarp convert "$DEMO/head.tif" -o "$DEMO/head_roundtrip.nrrd" --compress
volwarp info "$DEMO/head_roundtrip.nrrd" --json > "$DEMO/head_roundtrip.json"
if cmp -s <(volwarp info "$SCAN" --json | grep -v '"format"') \
          <(grep -v '"format"' "$DEMO/head_roundtrip.json"); then
  echo "round trip: identical samples, geometry and key/values"
else
  echo "round trip changed the volume" >&2; exit 1
fi

printf '\ndemo outputs in %s/:\n' "$DEMO"
ls -1 "$DEMO"
