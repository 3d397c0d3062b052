#!/usr/bin/env bash
# Converts inputs into one archive on a Slurm cluster: a prepare job (`canopy convert
# --work`: import, textures, partition into chunks) that submits a job array with one task
# per chunk (`--chunk K`, each on whichever node runs it) and a join job that runs once every
# chunk succeeded (`--join`, --dependency=afterok). The archive is the bytes `canopy
# convert` writes in one process with the same options. Prints the prepare job's id.
#
#   canopy-convert.sh OUT.canopy INPUT... [--concurrent K] [--work DIR]
#                     [convert options, e.g. --mem-budget 4GiB --scene s.toml]
#
# The inputs, OUT.canopy and the work directory (default OUT.canopy.work/: chunk files,
# job scripts, logs) must be on storage every node sees, as must the canopy binary ($CANOPY,
# default: canopy on PATH). --mem per job is --mem-budget plus 256 MiB (2 GiB budget by
# default). --concurrent K runs at most K chunk tasks at once (sbatch --array=...%K).
set -euo pipefail
. "$(dirname "$0")/lib.sh"

[ $# -ge 2 ] || usage
case $1 in -h|--help) usage ;; esac
out=$1
shift
canopy=${CANOPY:-canopy}
budget='' concurrent='' work=''
inputs=()
opts=()
while [ $# -gt 0 ]; do
    case $1 in
        --concurrent|--work|--mem-budget|--scene|--page-nodes|--zstd-level|--bvh|--missing-textures)
            [ $# -ge 2 ] || fail "$1 needs a value" ;;
    esac
    case $1 in
        --concurrent) concurrent=$2; shift 2 ;;
        --work) work=$2; shift 2 ;;
        --mem-budget) budget=$2; opts+=(--mem-budget "$budget"); shift 2 ;;
        --scene|--page-nodes|--zstd-level|--bvh|--missing-textures) opts+=("$1" "$2"); shift 2 ;;
        --chunk|--join|-o|--output|--json) fail "$1 is set by canopy-convert.sh" ;;
        -h|--help) usage ;;
        -*) opts+=("$1"); shift ;;
        *) inputs+=("$1"); shift ;;
    esac
done
[ ${#inputs[@]} -gt 0 ] || fail "no input files"
[ -z "$concurrent" ] || whole "$concurrent" || fail "--concurrent K must be a positive whole number"
for f in "${inputs[@]}"; do [ -f "$f" ] || fail "$f: no such input file"; done
command -v "$canopy" >/dev/null || fail "$canopy: not found (set CANOPY to the canopy binary)"
command -v sbatch >/dev/null || fail "sbatch not found: is Slurm installed here?"

mem=2304
[ -z "$budget" ] || mem=$(mem_mib "$budget") || fail "--mem-budget '$budget' is not a size"

mkdir -p "$(dirname "$out")"
out=$(abs "$out")
work=${work:-$out.work}
mkdir -p "$work/jobs"
work=$(abs "$work")
jobs=$work/jobs
abs_inputs=()
for f in "${inputs[@]}"; do abs_inputs+=("$(abs "$f")"); done
canopy=$(command -v "$canopy")

{
    echo '#!/usr/bin/env bash'
    printf 'exec %q --quiet convert --work %q --chunk "$SLURM_ARRAY_TASK_ID"\n' "$canopy" "$work"
} > "$jobs/chunk.sh"
{
    echo '#!/usr/bin/env bash'
    printf 'exec %q --quiet convert --work %q --join\n' "$canopy" "$work"
} > "$jobs/join.sh"
{
    echo '#!/usr/bin/env bash'
    echo 'set -euo pipefail'
    printf '%q --quiet convert' "$canopy"
    quoted "${abs_inputs[@]}"
    printf ' -o %q --work %q --json' "$out" "$work"
    quoted "${opts[@]}"
    printf ' > %q\n' "$jobs/prepare.json"
    printf 'n=$(sed -n %q %q)\n' 's/^ *"chunks": \([0-9]*\),*$/\1/p' "$jobs/prepare.json"
    printf 'range="0-$((n - 1))%s"\n' "${concurrent:+%$concurrent}"
    printf 'array=$(sbatch --parsable --job-name=canopy-chunk --array="$range" --mem=%dM -o %q %q)\n' \
        "$mem" "$jobs/chunk_%a.log" "$jobs/chunk.sh"
    echo 'array=${array%%;*}'
    printf 'join=$(sbatch --parsable --job-name=canopy-join --dependency="afterok:$array" --mem=%dM -o %q %q)\n' \
        "$mem" "$jobs/join.log" "$jobs/join.sh"
    echo 'echo "chunks: job ${array} ($n tasks); join: job ${join%%;*}"'
} > "$jobs/prepare.sh"
chmod +x "$jobs/chunk.sh" "$jobs/join.sh" "$jobs/prepare.sh"

prepare=$(sbatch --parsable --job-name=canopy-prepare --mem="${mem}M" -o "$jobs/prepare.log" \
    "$jobs/prepare.sh")
prepare=${prepare%%;*}
echo "prepare: job $prepare (submits the chunk array and the join; logs in $jobs)"
echo "archive: $out once the join succeeded"
