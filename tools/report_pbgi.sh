#!/bin/sh
# PBGI at its defaults against the path tracer, both judged against the Mitsuba 3 full-GI
# references in scenes/refs: `canopy eval --integrators path,pbgi --times 60s --threads 1`
# on room, bunny_box, showroom (glossy) and sponza_textured, seeds 1–5, two evals at a time
# (one thread each). PBGI's 60 s include its bake. Prints, per scene, the median over the
# seeds of (c_path / c_pbgi)², c = RMSE·√seconds: how much sooner PBGI reaches the path
# tracer's error. Results go to OUT (default /tmp/canopy_pbgi_report); about 25 minutes.
# Usage: sh tools/report_pbgi.sh [OUT]
set -eu
cd "$(dirname "$0")/.."
OUT="${1:-/tmp/canopy_pbgi_report}"
cargo build --release
BIN=target/release/canopy
mkdir -p "$OUT"
convert() {
    case "$1" in
    sponza_textured) in="scenes/sponza_textured/sponza_textured.gltf" ;;
    *) in="scenes/$1.glb" ;;
    esac
    [ -f "$OUT/$1.canopy" ] || $BIN --quiet convert "$in" -o "$OUT/$1.canopy" > /dev/null
}
run() {
    $BIN --quiet eval "$OUT/$1.canopy" --reference "scenes/refs/$1.exr" \
        --integrators path,pbgi --times 60s --seed "$2" --threads 1 -o "$OUT/$1_$2" > /dev/null
    rm -f "$OUT/$1_$2"/*.exr
}
for scene in room bunny_box showroom sponza_textured; do convert "$scene"; done
for seed in 1 2 3 4 5; do
    run room "$seed" & run bunny_box "$seed"; wait
    run showroom "$seed" & run sponza_textured "$seed"; wait
done
for scene in room bunny_box showroom sponza_textured; do
    for seed in 1 2 3 4 5; do
        awk -F, '$1 == "Path" { p = $NF } $1 == "Pbgi" { q = $NF } END { print (p / q) ^ 2 }' \
            "$OUT/${scene}_$seed/eval.csv"
    done | sort -g | awk -v s="$scene" '{ v[NR] = $1 } END { printf "%s: median %.2fx (%.2f to %.2fx)\n", s, v[3], v[1], v[5] }'
done
