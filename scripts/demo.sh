#!/usr/bin/env bash
# The main job on the bundled sample (a real T1 head MRI, tests/data/): called by `make demo`.
# Every subcommand once, on real files: capture + warp the head, mesh and render it,
# its signed distance field, a head-to-brain morph, and a swept milk bottle.
# Writes everything under $DEMO (default demo-output/).
set -euo pipefail
cd "$(dirname "$0")/.."
DEMO=${DEMO:-demo-output}
BIN=${BIN:-.venv/bin}
case "$BIN" in /*) ;; *) BIN="$PWD/$BIN" ;; esac  # (make passes a relative or an absolute one)
export PATH="$BIN:$PATH"
mkdir -p "$DEMO"
SCAN=tests/data/mri_t1_head_coronal_2x2x3mm.nrrd
BRAIN=tests/data/mri_colin27_brain_1mm.nrrd
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

step "capture + warp: raise the crown by 20 mm, push the patient's left side in (specs/warp-head.yaml)"
volwarp capture "$SCAN" -o "$DEMO/head.vwc" --lattice 9 --oversample 1
volwarp warp "$DEMO/head.vwc" --spec specs/warp-head.yaml -o "$DEMO/head_warped.nrrd" -v

step "mesh: skin surfaces (iso 60) of the warp and of the scan, rendered by one camera"
# (the warp first: its camera frames the raised crown, which leaves the scan's box)
volwarp mesh "$DEMO/head_warped.nrrd" --iso 60 --cap --largest-component -o "$DEMO/head_warped.ply" \
  --view patient-left --color skin --render "$DEMO/head_warped.png" \
  --camera-to "$DEMO/head_camera.json" --stats
volwarp mesh "$SCAN" --iso 60 --cap --largest-component -o "$DEMO/head.ply" \
  --camera-from "$DEMO/head_camera.json" --color skin --render "$DEMO/head.png" --stats

step "distance: signed distance to the skin (mm, negative inside), and its zero level"
volwarp distance "$SCAN" --iso 40 -o "$DEMO/head_sdf.nrrd" -v
volwarp mesh "$DEMO/head_sdf.nrrd" --iso 0 --inside below --cap --largest-component -o "$DEMO/head_sdf0.ply" \
  --stats

step "morph: the head into the Colin27 brain, 5 frames, meshes and a contact sheet"
volwarp morph --spec specs/morph-head-brain.yaml -o "$DEMO/morph_{i:02d}.nrrd" \
  --mesh-to "$DEMO/morph_{i:02d}.ply" --render-to "$DEMO/morph_{i:02d}.png" \
  --sheet "$DEMO/morph_sheet.png" --render-size 320x320

step "sweep: a milk bottle by rotational sweep (Winter & Chen Fig. 1)"
mkdir -p "$DEMO/sweep"
volwarp sweep specs/sweep-bottle.yaml -o "$DEMO/sweep/bottle_{field}.nrrd" \
  --spacing 0.3 --render "$DEMO/bottle.png" --view -70,25

step "one picture of it all: demo-output/demo.png"
python - "$DEMO" <<'EOF'
import sys
from volwarp_cli.io.images import read_image, write_image
from volwarp_cli.render.sheet import contact_sheet
d = sys.argv[1]
names = ["head.png", "head_warped.png", "morph_sheet.png", "bottle.png"]
titles = ["the bundled MRI (iso 60)", "warped: crown raised, left side pushed in",
          "morph: head to brain", "a swept milk bottle"]
write_image(f"{d}/demo.png", contact_sheet([read_image(f"{d}/{n}")[..., :3] for n in names],
                                           columns=2, titles=titles))
EOF

printf '\ndemo outputs in %s/:\n' "$DEMO"
ls -1 "$DEMO"
