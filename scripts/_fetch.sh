# Shared by the download scripts (sourced, not run).

die() { echo "error: $*" >&2; exit 1; }

fetch() {  # fetch URL FILE: download to FILE.part, then rename, so an interrupted run leaves no bad zip
    local url="$1" out="$2"
    if command -v curl >/dev/null 2>&1; then
        curl -fL --retry 3 --progress-bar -o "$out.part" "$url"
    elif command -v wget >/dev/null 2>&1; then
        wget -q --show-progress -O "$out.part" "$url"
    else
        die "need curl or wget to download $url"
    fi
    mv "$out.part" "$out"
}

install_dir() {  # install_dir SRC DEST: replace DEST with the finished SRC in one rename
    rm -rf "$2"
    mkdir -p "$(dirname "$2")"
    mv "$1" "$2"
}
