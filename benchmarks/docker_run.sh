#!/usr/bin/env bash
# Time the image's commands as a user runs them: a docker run each of fit, update,
# query (one point, then a CSV file) and plot, on a store in a mounted scratch directory.
#
#   bash benchmarks/docker_run.sh [IMAGE] [NATIONAL_GTX] [POINTS_CSV]
#
# IMAGE defaults to geoidspline (docker build -t geoidspline .). NATIONAL_GTX is the grid
# of the regional update (it must cover -46..-14 N, -82..-48 E: the update region
# -40 -75 -20 -55 and its 100 km blend); POINTS_CSV rows lat,lon with a header. Without
# them the update and the CSV query are skipped. Prints the image size, then one line per
# command: seconds of the whole docker run, milliseconds of the command inside the
# container, and the command's last output line.
set -euo pipefail
image="${1:-geoidspline}"
national="${2:-}"
points="${3:-}"
work="$(mktemp -d "${TMPDIR:-/tmp}/docker_run.XXXXXX")"
trap 'rm -rf "$work"' EXIT
chmod 777 "$work"  # the image's user (uid 1000) writes the store here
[ -n "$national" ] && install -m 644 "$national" "$work/national.gtx"
[ -n "$points" ] && install -m 644 "$points" "$work/points.csv"

echo "image $image: $(docker image inspect -f '{{.Size}}' "$image") bytes"
# each command timed twice: the whole `docker run` (container set-up included, which the
# storage driver dominates: vfs copies the image for every container) and the command
# inside the container
run() {
  local name="$1"; shift
  local start end out inside
  start=$(date +%s.%N)
  out="$(docker run --rm -v "$work:/data" "$image" sh -c \
    's=$(date +%s%N); "$@"; rc=$?; e=$(date +%s%N); echo "inside $(( (e - s) / 1000000 )) ms"; exit $rc' sh "$@" 2>&1)" \
    || { echo "$name FAILED: $out"; return 1; }
  end=$(date +%s.%N)
  inside="$(printf '%s\n' "$out" | tail -1)"
  printf '%-8s docker run %7.2f s, %s  | %s\n' "$name" "$(awk "BEGIN {print $end - $start}")" "$inside" \
    "$(printf '%s\n' "$out" | tail -2 | head -1)"
}
run none    true
run fit     geoid-fit egm96-15 --region -60 -90 15 -30 --tolerance 0.5 --store /data/andes
run query   geoid-query --store /data/andes -33.45 -70.66
if [ -n "$national" ]; then
  run update  geoid-update /data/national.gtx --store /data/andes --region -40 -75 -20 -55 --blend-width 100
fi
if [ -n "$points" ]; then
  run csv   sh -c 'geoid-query --store /data/andes --input /data/points.csv > /data/out.csv && wc -l < /data/out.csv'
fi
run plot    geoid-plot --store /data/andes --out /data/andes.png
run levels  geoid-plot --store /data/andes --map levels --out /data/andes-levels.png
run info    geoid-info --store /data/andes --verify
