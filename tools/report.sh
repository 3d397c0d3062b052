#!/bin/sh
# The default speed-against-error report on the bundled scenes: converts cbox, bunny_box,
# room, room_glossy, room_glass, showroom, caustics and the glTF scenes bumps (normal maps)
# and sponza_textured, runs `canopy eval` (path, cone and PBGI at 5, 15 and 60 seconds; on
# showroom also PBGI gathering through the cut, in showroom_cut/) against the Mitsuba 3
# references in scenes/refs (sponza_textured's has 1024 spp: its noise floors the RMSE
# there), and `canopy npp` (both
# integrators, to 10% noise) on bunny_box. Results go to docs/report/<scene>/ (eval.csv,
# eval.md, eval.svg; npp.csv, npp.svg). Takes about 4 minutes a scene.
# Usage: sh tools/report.sh [TIMES]   e.g. TIMES=2s,5s,15s for a quick run
set -eu
cd "$(dirname "$0")/.."
TIMES="${1:-5s,15s,60s}"
cargo build --release
BIN=target/release/canopy
OUT=docs/report
mkdir -p "$OUT"
for input in cbox.glb bunny_box.glb room.glb room_glossy.glb room_glass.glb showroom.glb \
    caustics.glb bumps/bumps.gltf sponza_textured/sponza_textured.gltf; do
    scene=$(basename "$input" | sed 's/\.gl[bt]f*$//')
    $BIN --quiet convert "scenes/$input" -o "$OUT/$scene.canopy" > /dev/null
    $BIN --quiet eval "$OUT/$scene.canopy" --reference "scenes/refs/$scene.exr" \
        --integrators path,cone,pbgi --times "$TIMES" -o "$OUT/$scene"
    rm -f "$OUT/$scene"/*.exr "$OUT/$scene"/eval_*.json
done
$BIN --quiet eval "$OUT/showroom.canopy" --reference scenes/refs/showroom.exr \
    --integrators pbgi --pbgi-gather cut --times "$TIMES" -o "$OUT/showroom_cut"
rm -f "$OUT/showroom_cut"/*.exr "$OUT/showroom_cut"/eval_*.json
$BIN --quiet npp "$OUT/bunny_box.canopy" --integrators path,cone,pbgi --resolutions 32,64,128,256 --noise 0.1 --spp 256 \
    -o "$OUT/bunny_box_npp"
rm -f "$OUT"/*.canopy "$OUT/bunny_box_npp"/*.exr "$OUT/bunny_box_npp"/npp_*.json
echo "report in $OUT"
