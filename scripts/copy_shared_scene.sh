#!/usr/bin/env bash
# Copy a scene from the shared data folder into data/raw/NAME, where conf/scene/*.yaml expects it.
#
# Idempotent: re-running brings data/raw/NAME back in line with the source (rsync --delete, or a
# fresh copy renamed into place when rsync is absent).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    cat >&2 <<USAGE
usage: $(basename "$0") NAME [SHARED_DIR]

Copies SHARED_DIR/scenes/NAME to $REPO/data/raw/NAME.
SHARED_DIR defaults to the folder 'shared' next to the repository ($REPO/../shared).
USAGE
    exit 2
}

die() { echo "error: $*" >&2; exit 1; }

[[ $# -ge 1 && $# -le 2 ]] || usage
name="$1"
[[ -n "$name" && "$name" != */* && "$name" != .* ]] || die "NAME must be a plain folder name, got '$name'"
shared="${2:-$REPO/../shared}"
[[ -d "$shared" ]] || die "shared folder $shared does not exist"
src="$(cd "$shared" && pwd)/scenes/$name"
[[ -d "$src" ]] || die "scene folder $src does not exist"
dest="$REPO/data/raw/$name"
mkdir -p "$REPO/data/raw"

if command -v rsync >/dev/null 2>&1; then
    rsync -a --delete "$src/" "$dest/"
else
    tmp="$dest.tmp.$$"
    trap 'rm -rf "$tmp"' EXIT
    rm -rf "$tmp"
    cp -R "$src" "$tmp"
    rm -rf "$dest"
    mv "$tmp" "$dest"
fi
echo "copied $src -> $dest ($(find "$dest" -type f | wc -l) files)"
