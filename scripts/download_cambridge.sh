#!/usr/bin/env bash
# Download raw Cambridge Landmarks scenes into data/raw/cambridge_<short> (import with format "cambridge").
#
# Each archive <Scene>.zip holds <Scene>/{dataset_train.txt,dataset_test.txt,reconstruction.nvm,seq*/}.
# The University of Cambridge repository has moved its file links before, so every scene also
# accepts an explicit URL or an already downloaded zip: SHORT=URL or SHORT=/path/to/Scene.zip.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RAW_DIR="${USVC_RAW_DIR:-$REPO/data/raw}"
HANDLE="https://www.repository.cam.ac.uk/bitstream/handle/1810"
declare -A FOLDER=(
    [kings]=KingsCollege [hospital]=OldHospital [shop]=ShopFacade
    [church]=StMarysChurch [court]=GreatCourt [street]=Street
)
declare -A URL=(
    [kings]="$HANDLE/251342/KingsCollege.zip" [hospital]="$HANDLE/251340/OldHospital.zip"
    [shop]="$HANDLE/251336/ShopFacade.zip" [church]="$HANDLE/251294/StMarysChurch.zip"
    [court]="$HANDLE/251291/GreatCourt.zip" [street]="$HANDLE/251292/Street.zip"
)

usage() {
    cat >&2 <<USAGE
usage: $(basename "$0") SCENE[=URL|=ZIP] [SCENE[=URL|=ZIP]...]

Fetches Cambridge Landmarks scenes into \$USVC_RAW_DIR/cambridge_SCENE (default: $REPO/data/raw).
SCENE is one of: kings hospital shop church court street
(KingsCollege OldHospital ShopFacade StMarysChurch GreatCourt Street).

Without =..., the scene's archive is downloaded from
  $HANDLE/<id>/<Scene>.zip
If that link no longer works, download <Scene>.zip by hand from
  https://www.repository.cam.ac.uk/handle/1810/251342  (and the sibling records of the other scenes)
and pass it:  $(basename "$0") kings=/path/to/KingsCollege.zip
A scene folder that already holds dataset_train.txt, dataset_test.txt and reconstruction.nvm is skipped.
USAGE
    exit 2
}

# shellcheck source=scripts/_fetch.sh
. "$(dirname "${BASH_SOURCE[0]}")/_fetch.sh"

is_complete() {
    local dir="$1"
    [[ -f "$dir/dataset_train.txt" && -f "$dir/dataset_test.txt" && -f "$dir/reconstruction.nvm" ]]
}

install_scene() {
    local short="$1" source="$2"
    local folder="${FOLDER[$short]}"
    local dest="$RAW_DIR/cambridge_$short"
    if is_complete "$dest"; then
        echo "cambridge_$short: already complete in $dest"
        return
    fi
    local work="$RAW_DIR/.download_cambridge_$short"
    mkdir -p "$work"
    local zip
    if [[ "$source" =~ ^https?:// ]]; then
        zip="$work/$folder.zip"
        if [[ ! -f "$zip" ]]; then
            echo "cambridge_$short: downloading $source"
            fetch "$source" "$zip"
        fi
    else
        zip="$source"
        [[ -f "$zip" ]] || die "$zip is not a file"
    fi
    unzip -l "$zip" >/dev/null 2>&1 || die "$zip is not a valid zip archive (a login or HTML page instead of the data?)"
    rm -rf "$work/unpacked"
    mkdir -p "$work/unpacked"
    unzip -q "$zip" -d "$work/unpacked"
    local src="$work/unpacked/$folder"
    [[ -d "$src" ]] || die "$zip does not contain a folder $folder/"
    is_complete "$src" || die "$src lacks dataset_train.txt, dataset_test.txt or reconstruction.nvm"
    install_dir "$src" "$dest"
    rm -rf "$work"
    echo "cambridge_$short: ready in $dest"
}

[[ $# -ge 1 ]] || usage
command -v unzip >/dev/null 2>&1 || die "need unzip"
for arg in "$@"; do
    short="${arg%%=*}"
    [[ -n "${FOLDER[$short]+set}" ]] || { echo "unknown Cambridge scene: $short" >&2; usage; }
done
for arg in "$@"; do
    short="${arg%%=*}"
    if [[ "$arg" == *=* ]]; then
        source="${arg#*=}"
        [[ "$source" =~ ^https?:// ]] || source="$(cd "$(dirname "$source")" && pwd)/$(basename "$source")"
    else
        source="${URL[$short]}"
    fi
    install_scene "$short" "$source"
done
