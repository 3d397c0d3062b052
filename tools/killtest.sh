#!/usr/bin/env bash
# SIGKILL a conversion at N random moments and list what is left in its directory.
#   sh tools/killtest.sh INPUT [N] [--mem-budget SIZE ...]
# The input is copied into a fresh directory; after each kill the directory must hold the
# input alone (spill files and the archive being written have no name until complete).
set -eu
input=$1; n=${2:-20}; shift; shift || true
canopy=${CANOPY:-target/release/canopy}
dir=$(mktemp -d)
cp "$input" "$dir/in.${input##*.}"
start=$(date +%s%N)
"$canopy" convert "$dir/in.${input##*.}" -o "$dir/out.canopy" --quiet "$@" >/dev/null
full=$(( ($(date +%s%N) - start) / 1000000 ))
rm -f "$dir/out.canopy"
echo "a full conversion takes $full ms"
left=0
for i in $(seq "$n"); do
  at=$(( (RANDOM * 32768 + RANDOM) % full ))
  "$canopy" convert "$dir/in.${input##*.}" -o "$dir/out.canopy" --quiet "$@" >/dev/null 2>&1 &
  pid=$!
  sleep "$(awk "BEGIN{print $at/1000}")"
  kill -9 $pid 2>/dev/null && killed=yes || killed=no
  wait $pid 2>/dev/null || true
  extra=$(ls -A "$dir" | grep -v "^in\." | grep -v "^out.canopy$" || true)
  [ "$killed" = no ] && rm -f "$dir/out.canopy"
  if [ -e "$dir/out.canopy" ]; then extra="$extra out.canopy"; fi
  echo "kill $i at $at ms (killed: $killed): left ${extra:-nothing}"
  [ -n "$extra" ] && left=$((left + 1))
  rm -f "$dir/out.canopy"
done
rm -rf "$dir"
echo "$left of $n kills left something behind"
[ "$left" = 0 ]
