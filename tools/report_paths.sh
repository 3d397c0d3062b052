#!/bin/sh
# Speed against error on the same light paths (camera → x → y → light, `--max-depth 3`):
# path, cone, PBGI with texel rays and the cache (`--pbgi-rays --pbgi-reuse 256`), and
# PBGI with the cut (wavelet cube maps where the scene has glossy materials; on showroom
# also without them, and WPBGI, `--pbgi-glossy-bounce wavelet` and `cache`) on sponza, bunny_box and
# showroom, against the path tracer's own
# depth-3 references (Mitsuba's are full GI, which one-bounce PBGI cannot reach). Each
# `canopy eval` runs on one thread, two at a time. References are rendered once into
# REFS (8–10 minutes each on two cores) and reused. Results go to docs/report/paths/<scene>/.
# Usage: sh tools/report_paths.sh [REFS] [TIMES]   e.g. REFS=/tmp/refs TIMES=30s,60s
set -eu
cd "$(dirname "$0")/.."
REFS="${1:-/tmp/canopy_refs}"
TIMES="${2:-30s,60s}"
cargo build --release
BIN=target/release/canopy
OUT=docs/report/paths
mkdir -p "$OUT" "$REFS"
size() {
    case "$1" in
    sponza) echo "--width 200 --height 128 --time 480s" ;;
    bunny_box) echo "--width 128 --height 128 --time 240s" ;;
    showroom) echo "--width 128 --height 96 --time 600s" ;;
    esac
}
for scene in sponza bunny_box showroom; do
    arc="$REFS/$scene.canopy"
    [ -f "$arc" ] || $BIN --quiet convert "scenes/$scene.glb" -o "$arc" > /dev/null
    ref="$REFS/${scene}_d3.exr"
    # shellcheck disable=SC2046
    [ -f "$ref" ] || $BIN --quiet render "$arc" --max-depth 3 --seed 91 $(size "$scene") -o "$ref"
done
run() {
    scene=$1
    name=$2
    shift 2
    $BIN --quiet eval "$REFS/$scene.canopy" --reference "$REFS/${scene}_d3.exr" --times "$TIMES" \
        --max-depth 3 --seed 1 --threads 1 "$@" -o "$OUT/$scene/$name" > /dev/null
    rm -f "$OUT/$scene/$name"/*.exr "$OUT/$scene/$name"/eval_*.json
}
BB="--pbgi-resolution 16 --pbgi-cache 0.15"
# shellcheck disable=SC2086
{
    run sponza rays --integrators path,cone,pbgi --pbgi-rays --pbgi-reuse 256 &
    run bunny_box rays --integrators path,cone,pbgi --pbgi-rays --pbgi-reuse 256 $BB
    wait
    run showroom rays --integrators path,cone,pbgi --pbgi-rays --pbgi-reuse 256 &
    run sponza cut --integrators pbgi --pbgi-reuse 256
    wait
    run bunny_box cut --integrators pbgi --pbgi-reuse 256 $BB &
    run showroom cut --integrators pbgi --pbgi-reuse 256
    wait
    run showroom cut_flat --integrators pbgi --pbgi-reuse 256 --wavelet off &
    run showroom wpbgi --integrators path,pbgi --pbgi-rays --pbgi-reuse 256 --pbgi-glossy-bounce wavelet
    wait
    run showroom wpbgi_cache --integrators path,pbgi --pbgi-rays --pbgi-reuse 256 --pbgi-glossy-bounce cache

}
echo "report in $OUT"
