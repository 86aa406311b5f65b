#!/usr/bin/env bash
# The drone photos to a viewed, rendered and exported model, from a fresh clone, with the README's
# commands: clone, pip install -e ".[process]", photos -> poses (scalar-nerf-process-data, through
# tools/make_caliterra_scene.sh, which extracts the photos from the data set's repository first),
# ns-train scalar-nerf (default steps, images_8: 500 x 375), the viewer in headless Chromium
# (benchmarks/bench_viewer.py), ns-render dataset, ns-eval, ns-export pointcloud in the capture's frame,
# then the exported points against the sparse SfM points (check_export.py beside this script).
# Each step's wall time and peak memory (GNU time) go to WORK/steps.tsv.
#
#     docs/benchmark/caliterra/fresh-clone.sh REPO_URL_OR_PATH DATA_REPO WORK
#       REPO_URL_OR_PATH  this project (a URL or a local clone)
#       DATA_REPO         OpenDroneMap's odm_data_caliterra (a clone or a bare copy; photos are never committed)
#       WORK              a new folder for the clone, the scene and the run
# Needs: Python >= 3.10 with pip, g++, and what tools/setup-tests.sh installs (ffmpeg, libusb, chromium).
set -euo pipefail
[ $# -eq 3 ] || { sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
SOURCE=$1; DATA=$(cd "$2" && pwd); WORK=$3
mkdir -p "$WORK"; WORK=$(cd "$WORK" && pwd)
HERE=$(cd "$(dirname "$0")" && pwd)
export PYTHONWARNINGS=ignore
step() {  # name, command...: run it, record seconds and peak resident memory
    local name=$1; shift
    echo "=== $(date +%H:%M:%S) $name: $*"
    /usr/bin/time -f "%e %M" -o "$WORK/.time" "$@" > "$WORK/$name.log" 2>&1 || { echo "$name failed:"; tail -30 "$WORK/$name.log"; exit 1; }
    read -r seconds kib < "$WORK/.time"
    printf '%s\t%.0f s\t%.2f GiB\n' "$name" "$seconds" "$(echo "$kib / 1048576" | bc -l)" | tee -a "$WORK/steps.tsv"
}
: > "$WORK/steps.tsv"
step clone git clone --quiet "$SOURCE" "$WORK/clone"
cd "$WORK/clone"
step install python -m pip install --quiet -e ".[process]"
step process-data tools/make_caliterra_scene.sh "$DATA" "$WORK/scene"
grep -E "registered|reprojection|could not" "$WORK/process-data.log" || true
step train ns-train scalar-nerf --data "$WORK/scene" --output-dir "$WORK/outputs" --vis tensorboard nerfstudio-data --downscale-factor 8
RUN=$(dirname "$(find "$WORK/outputs" -name config.yml | head -1)")
grep -E "automatic K|K = " "$WORK/train.log" | head -3 || true
step viewer python benchmarks/bench_viewer.py --run "$RUN" --drag-seconds 3
tail -3 "$WORK/viewer.log"
step render ns-render dataset --load-config "$RUN/config.yml" --output-path "$WORK/renders" --split test
step eval ns-eval --load-config "$RUN/config.yml" --output-path "$WORK/eval.json"
step export ns-export pointcloud --load-config "$RUN/config.yml" --output-dir "$WORK/export" --save-world-frame True --num-points 200000
step check python "$HERE/check_export.py" --scene "$WORK/scene" --points "$WORK/export/point_cloud.ply"
cat "$WORK/check.log"
echo "=== done"; cat "$WORK/steps.tsv"
