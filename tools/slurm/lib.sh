# Shell helpers the Slurm scripts share (sourced, not run).

# The calling script's opening comment (its usage) on standard error; exit 2.
usage() {
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0" >&2
    exit 2
}

# "SCRIPT: message" on standard error; exit 2.
fail() {
    echo "$(basename "$0"): $*" >&2
    exit 2
}

# Whether $1 is a positive whole number.
whole() { [[ $1 =~ ^[1-9][0-9]*$ ]]; }

# --mem in MiB from a size like 512MiB, 2GiB, 1.5G or a byte count, plus 256 MiB for code,
# buffers and (rendering) the film.
mem_mib() {
    awk -v s="$1" 'BEGIN {
        if (match(s, /^[0-9.]+/) == 0) exit 1
        n = substr(s, 1, RLENGTH); u = toupper(substr(s, RLENGTH + 1)); sub(/I?B$/, "", u)
        f = (u == "") ? 1 : (u == "K") ? 1024 : (u == "M") ? 1048576 : (u == "G") ? 1073741824 : (u == "T") ? 1099511627776 : -1
        if (f < 0) exit 1
        printf "%d\n", n * f / 1048576 + 256 }'
}

# $1 as an absolute path (its directory must exist).
abs() { (cd "$(dirname "$1")" && printf '%s/%s\n' "$(pwd -P)" "$(basename "$1")"); }

# Each argument shell-quoted after a space (nothing for none).
quoted() { for a in "$@"; do printf ' %q' "$a"; done; }
