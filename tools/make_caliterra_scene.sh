#!/usr/bin/env bash
# Rebuild the Caliterra drone scene: OpenDroneMap's odm_data_caliterra (77 photos, 4000 x 3000, of a
# Canon PowerShot SX260 HS with EXIF GPS, looking down on a construction site) -> a nerfstudio scene with
# poses from scalar-nerf-process-data (pycolmap SfM on the CPU, spatial matching from GPS; metres,
# east-north-up).
#
# Usage:  tools/make_caliterra_scene.sh REPO SCENE [process-data options, e.g. --max-image-size 1600]
#   REPO   the data set's git repository, a clone or a bare copy:
#            git clone https://github.com/OpenDroneMap/odm_data_caliterra
#   SCENE  the scene folder to write (keep it outside this repository: photos are never committed).
# The photos are extracted to SCENE.photos/ (SCENE/images/ hard-links them); photos whose git blobs
# are missing from REPO (a partial copy) are skipped with a note. Run it again to resume.
# Needs the project with its process extra: pip install -e ".[process]".
set -euo pipefail
if [ $# -lt 2 ]; then
    sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
REPO=$1
SCENE=$2
shift 2
GIT_DIR=$(git -C "$REPO" rev-parse --absolute-git-dir 2>/dev/null) || { echo "$REPO: not a git repository" >&2; exit 1; }
GIT=(git --git-dir="$GIT_DIR")
PHOTOS="${SCENE%/}.photos"
mkdir -p "$PHOTOS"

total=0; written=0; missing=()
while read -r _mode _type blob path; do
    case "${path,,}" in *.jpg|*.jpeg) ;; *) continue ;; esac
    total=$((total + 1))
    name=$(basename "$path")
    if ! "${GIT[@]}" cat-file -e "$blob" 2>/dev/null; then
        missing+=("$name")
        continue
    fi
    if [ -f "$PHOTOS/$name" ] && [ "$(git hash-object "$PHOTOS/$name")" = "$blob" ]; then
        continue  # extracted earlier
    fi
    "${GIT[@]}" cat-file blob "$blob" > "$PHOTOS/.$name.tmp"
    mv "$PHOTOS/.$name.tmp" "$PHOTOS/$name"
    written=$((written + 1))
done < <("${GIT[@]}" ls-tree -r HEAD -- images/)

echo "$((total - ${#missing[@]})) of $total photos in $PHOTOS ($written extracted now)"
if [ ${#missing[@]} -gt 0 ]; then
    echo "note: ${#missing[@]} photo(s) skipped, their blobs are missing from $REPO: ${missing[*]}"
fi
exec python -m scalar_nerfstudio.scripts.process_data --images "$PHOTOS" --output "$SCENE" --matching spatial "$@"
