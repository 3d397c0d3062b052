#!/bin/bash
# Renders a fixed-seed set with two canopy binaries and says which images differ in any
# pixel (canopy compare --metric mae): the check that a refactoring changed no image.
#   bash tools/same_images.sh OLD_CANOPY NEW_CANOPY [WORKDIR]
# Path-tracer renders use all threads (they are thread-count independent), cone and PBGI
# renders one.
set -u
OLD=$1 NEW=$2 W=${3:-$(mktemp -d)}
S=$(cd "$(dirname "$0")/.." && pwd)/scenes
mkdir -p "$W/old" "$W/new"
for s in cbox bunny_box caustics sponza; do
  [ -f "$W/$s.canopy" ] || "$OLD" --quiet convert "$S/$s.glb" -o "$W/$s.canopy" >/dev/null || exit 1
done
# Textures and alpha masks (the chains and leaves).
[ -f "$W/spt.canopy" ] || "$OLD" --quiet convert "$S/sponza_textured/sponza_textured.gltf" -o "$W/spt.canopy" >/dev/null || exit 1
set_of_renders() {
  echo "p_cbox cbox --spp 16 --width 128 --height 128"
  echo "p_cbox_d3 cbox --spp 16 --width 96 --height 96 --max-depth 3"
  echo "p_bunny bunny_box --spp 8 --width 128 --height 128"
  echo "p_caus caustics --spp 8 --width 128 --height 128"
  echo "p_sponza sponza --spp 4 --width 160 --height 100"
  echo "p_sponza_t1 sponza --spp 2 --width 96 --height 64 --threads 1 --mem-budget 64MiB"
  echo "p_crop cbox --spp 8 --width 128 --height 128 --crop 10,70,20,90"
  echo "p_spt spt --spp 4 --width 160 --height 100"
  echo "c_cbox cbox --integrator cone --threads 1 --spp 8 --width 96 --height 96"
  echo "c_cbox_d3 cbox --integrator cone --threads 1 --spp 8 --width 96 --height 96 --max-depth 3"
  echo "c_bunny bunny_box --integrator cone --threads 1 --spp 8 --width 96 --height 96"
  echo "c_caus caustics --integrator cone --threads 1 --spp 8 --width 96 --height 96"
  echo "c_caus_off caustics --integrator cone --threads 1 --spp 4 --width 96 --height 96 --light-pass off --edge-rays 0"
  echo "c_sponza sponza --integrator cone --threads 1 --spp 4 --width 96 --height 64"
  echo "c_spt spt --integrator cone --threads 1 --spp 2 --width 96 --height 64"
  echo "pb_cbox cbox --integrator pbgi --threads 1 --spp 2 --width 64 --height 64"
  echo "pb_spt spt --integrator pbgi --threads 1 --spp 1 --width 64 --height 40"
  echo "pb_bunny bunny_box --integrator pbgi --threads 1 --spp 6 --width 48 --height 48"
  echo "c_sponza_b sponza --integrator cone --threads 1 --spp 4 --width 96 --height 64 --mem-budget 48MiB --cone-scale 2 --diffuse-tan 0.1 --cone-samples 64"
}
diff=0
while read -r name scene args; do
  for v in old new; do
    bin=$OLD; [ $v = new ] && bin=$NEW
    # shellcheck disable=SC2086
    "$bin" --quiet render "$W/$scene.canopy" -o "$W/$v/$name.exr" --seed 7 $args >/dev/null || exit 1
  done
  e=$("$NEW" compare "$W/new/$name.exr" "$W/old/$name.exr" --metric mae --json | sed -n 's/.*"error": \([^,]*\),*/\1/p')
  if [ "$e" = "0.0" ]; then echo "same       $name"; else echo "DIFFERENT  $name (mae $e)"; diff=1; fi
done < <(set_of_renders)
exit $diff
