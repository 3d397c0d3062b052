#!/usr/bin/env bash
# Renders one frame on a Slurm cluster as horizontal tiles: a job array with one task per
# tile (`canopy render --crop`, each under its own --mem), then an assembly job that runs
# once every tile succeeded (`canopy assemble`, --dependency=afterok). Prints the job ids.
# With --integrator cone, a pre-pass at a quarter of the resolution writes the stored light
# (--store-out) and every tile starts from it (--store-in), so tiles show no seams.
#
#   canopy-frame.sh ARCHIVE OUT.exr --tiles N --width W --height H [--concurrent K]
#                   [render options, e.g. --spp 256 --seed 1 --mem-budget 2GiB]
#
# ARCHIVE, OUT.exr and OUT.exr.tiles/ (tiles, job scripts, logs) must be on storage every
# node sees. The canopy binary is $CANOPY (default: canopy on PATH), also as every node
# sees it. --mem per task is --mem-budget plus 256 MiB for code, film and buffers (2 GiB
# without a budget). --concurrent K runs at most K tiles at once (sbatch --array=...%K).
set -euo pipefail
. "$(dirname "$0")/lib.sh"

[ $# -ge 2 ] || usage
case $1 in -h|--help) usage ;; esac
archive=$1
out=$2
shift 2
canopy=${CANOPY:-canopy}
tiles='' width='' height='' budget='' concurrent='' integrator=path
opts=()
while [ $# -gt 0 ]; do
    case $1 in
        --tiles|--concurrent|--width|--height|--mem-budget) [ $# -ge 2 ] || fail "$1 needs a value" ;;
    esac
    case $1 in
        --tiles) tiles=${2-}; shift 2 ;;
        --concurrent) concurrent=${2-}; shift 2 ;;
        --width) width=${2-}; shift 2 ;;
        --height) height=${2-}; shift 2 ;;
        --integrator) [ $# -ge 2 ] || fail "$1 needs a value"; integrator=$2; opts+=("$1" "$2"); shift 2 ;;
        --store-in|--store-out) fail "$1 is set by canopy-frame.sh (the pre-pass writes the store)" ;;
        --mem-budget) budget=${2-}; opts+=(--mem-budget "$budget"); shift 2 ;;
        --crop|-o|--output|--stats) fail "$1 is set by canopy-frame.sh per tile" ;;
        -h|--help) usage ;;
        *) opts+=("$1"); shift ;;
    esac
done
whole "$tiles" || fail "--tiles N (a positive whole number) is required"
whole "$width" && whole "$height" || fail "--width and --height are required (the frame's size decides the tiles)"
[ "$tiles" -le "$height" ] || fail "--tiles $tiles is more than the $height rows of the frame"
[ -z "$concurrent" ] || whole "$concurrent" || fail "--concurrent K must be a positive whole number"
[ -f "$archive" ] || fail "$archive: no such archive"
command -v "$canopy" >/dev/null || fail "$canopy: not found (set CANOPY to the canopy binary)"
command -v sbatch >/dev/null || fail "sbatch not found: is Slurm installed here?"

mem=2048
[ -z "$budget" ] || mem=$(mem_mib "$budget") || fail "--mem-budget '$budget' is not a size"

archive=$(abs "$archive")
mkdir -p "$(dirname "$out")"
out=$(abs "$out")
dir="$out.tiles"
mkdir -p "$dir"
canopy=$(command -v "$canopy")

shared=()
after=()
if [ "$integrator" = cone ]; then
    shared=(--store-in "$dir/light.store")
    {
        echo '#!/usr/bin/env bash'
        printf 'exec %q --quiet render %q -o %q --store-out %q --width %d --height %d' \
            "$canopy" "$archive" "$dir/prepass.exr" "$dir/light.store" \
            $(( (width + 3) / 4 )) $(( (height + 3) / 4 ))
        quoted "${opts[@]}"
        echo
    } > "$dir/prepass.sh"
    chmod +x "$dir/prepass.sh"
    pre=$(sbatch --parsable --job-name=canopy-prepass --mem="${mem}M" -o "$dir/prepass.log" \
        "$dir/prepass.sh")
    pre=${pre%%;*}
    after=(--dependency="afterok:$pre")
    echo "pre-pass: job $pre (stored light -> $dir/light.store)"
fi
{
    echo '#!/usr/bin/env bash'
    echo 'set -euo pipefail'
    echo "i=\$SLURM_ARRAY_TASK_ID"
    echo "y0=\$(( i * $height / $tiles )); y1=\$(( (i + 1) * $height / $tiles ))"
    printf 'exec %q --quiet render %q -o %q --crop 0,%d,$y0,$y1 --stats %q --width %d --height %d' \
        "$canopy" "$archive" "$dir/tile_\$i.exr" "$width" "$dir/tile_\$i.json" "$width" "$height"
    quoted "${opts[@]}" "${shared[@]}"
    echo
} > "$dir/tile.sh"
# %q quotes the $ of the task's variables; let the task's shell expand them.
sed -i 's/\\\$i/$i/g; s/\\\$y0/$y0/g; s/\\\$y1/$y1/g' "$dir/tile.sh"
{
    echo '#!/usr/bin/env bash'
    printf 'exec %q assemble' "$canopy"
    for ((i = 0; i < tiles; i++)); do printf ' %q' "$dir/tile_$i.exr"; done
    printf ' -o %q\n' "$out"
} > "$dir/assemble.sh"
chmod +x "$dir/tile.sh" "$dir/assemble.sh"

range="0-$((tiles - 1))${concurrent:+%$concurrent}"
array=$(sbatch --parsable --job-name=canopy-tile --array="$range" --mem="${mem}M" "${after[@]}" \
    --cpus-per-task=1 -o "$dir/tile_%a.log" "$dir/tile.sh")
array=${array%%;*}
assembly=$(sbatch --parsable --job-name=canopy-assemble --dependency="afterok:$array" \
    --mem=$(( 256 + width * height * 64 / 1048576 ))M -o "$dir/assemble.log" "$dir/assemble.sh")
assembly=${assembly%%;*}
echo "tiles: job $array ($tiles tasks, logs in $dir)"
echo "assembly: job $assembly (runs after every tile succeeded) -> $out"
