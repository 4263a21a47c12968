#!/usr/bin/env bash
# Download raw Microsoft 7-Scenes scenes into data/raw/7scenes_<scene> (import with format "7scenes").
#
# Each public archive <scene>.zip holds <scene>/{TrainSplit.txt,TestSplit.txt,seq-XX.zip};
# the inner per-sequence zips are unpacked in place and then deleted. Re-running skips scenes
# that are already complete. Needs curl or wget, and unzip.
set -euo pipefail

BASE_URL="https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8"
SCENES=(chess fire heads office pumpkin redkitchen stairs)
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RAW_DIR="${USVC_RAW_DIR:-$REPO/data/raw}"

usage() {
    cat >&2 <<USAGE
usage: $(basename "$0") SCENE [SCENE...]
       $(basename "$0") all

Downloads the raw 7-Scenes archives from Microsoft into \$USVC_RAW_DIR/7scenes_SCENE
(default: $REPO/data/raw). SCENE is one of: ${SCENES[*]}.
A scene folder that already holds TrainSplit.txt, TestSplit.txt and its sequences is skipped.
USAGE
    exit 2
}

# shellcheck source=scripts/_fetch.sh
. "$(dirname "${BASH_SOURCE[0]}")/_fetch.sh"

is_complete() {  # is_complete DIR: split files present and every listed sequence unpacked
    local dir="$1" seq
    [[ -f "$dir/TrainSplit.txt" && -f "$dir/TestSplit.txt" ]] || return 1
    for seq in $(cat "$dir/TrainSplit.txt" "$dir/TestSplit.txt" | tr -d '\r' | sed -n 's/^sequence\([0-9]*\)$/\1/p'); do
        compgen -G "$dir/$(printf 'seq-%02d' "$((10#$seq))")/frame-*.color.png" >/dev/null || return 1
    done
}

download_scene() {
    local scene="$1"
    local dest="$RAW_DIR/7scenes_$scene"
    if is_complete "$dest"; then
        echo "7scenes_$scene: already complete in $dest"
        return
    fi
    local work="$RAW_DIR/.download_7scenes_$scene"
    mkdir -p "$work"
    local zip="$work/$scene.zip"
    if [[ ! -f "$zip" ]]; then
        echo "7scenes_$scene: downloading $BASE_URL/$scene.zip"
        fetch "$BASE_URL/$scene.zip" "$zip"
    fi
    rm -rf "$work/unpacked"
    mkdir -p "$work/unpacked"
    unzip -q "$zip" -d "$work/unpacked"
    local src="$work/unpacked/$scene"
    [[ -d "$src" ]] || die "$zip does not contain a folder $scene/"
    local inner
    for inner in "$src"/seq-*.zip; do
        [[ -e "$inner" ]] || die "$zip holds no seq-XX.zip archives"
        unzip -q -o "$inner" -d "$src"
        rm -f "$inner"
    done
    find "$src" -name Thumbs.db -type f -delete
    is_complete "$src" || die "$zip unpacked, but $src lacks split files or sequences"
    install_dir "$src" "$dest"
    rm -rf "$work"
    echo "7scenes_$scene: ready in $dest"
}

[[ $# -ge 1 ]] || usage
command -v unzip >/dev/null 2>&1 || die "need unzip"
requested=("$@")
[[ "$1" == "all" ]] && requested=("${SCENES[@]}")
for scene in "${requested[@]}"; do
    [[ " ${SCENES[*]} " == *" $scene "* ]] || { echo "unknown 7-Scenes scene: $scene" >&2; usage; }
done
for scene in "${requested[@]}"; do
    download_scene "$scene"
done
