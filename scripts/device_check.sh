#!/usr/bin/env bash
# One call on a GPU machine that measures usvc's GPU path: the CUDA tests, the bundled scene from
# scratch with every stage on the device (seconds per stage, samples/s, the same map twice, the
# training step's profile), a 640 x 480 query, a folder of photos (worker threads and worker
# processes), `usvc serve` under load (640 x 480 photos, 1 and 16 clients, the network batched),
# and the training step at a larger batch; with --real NAME, a real scene's every stage
# from its photos too (data/raw/NAME carried beside the checkout: bird's 1.6 MB fit). Each step has its
# own time limit, cut to what is left of one budget counted from the start (--budget, 570 s: the
# whole script fits one ten-minute call whatever each step takes), and runs even when one before
# it failed; `steps.txt` says how each ended.
#
#   bash scripts/device_wheels.sh            # here, with network: the wheels such a machine lacks
#   bash scripts/device_check.sh             # there (the checkout and .whl/ carried beside it)
#   bash scripts/device_check.sh --real bird # the same, then bird from its photos (carry data/raw/bird)
#   bash scripts/device_check.sh --quick     # anywhere, in minutes: the same steps, short (CPU too)
#   bash scripts/device_check.sh --scaling 3840  # instead of those steps: the generated room at 3,840
#                                            # mapping frames, every stage on the device (benchmarks.pipeline scaling)
#
# Everything goes to $OUT (default results/device/): device.txt (the card, torch, COLMAP), steps.txt,
# benchmarks/*.json (each benchmark's report), logs/<step>.log. Where DIR (--wheels, default .whl/)
# exists, its wheels are installed offline first and DIR/src joins PYTHONPATH; the checkout is
# used in place (PYTHONPATH), not installed.
set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
wheels="$REPO/.whl"
quick=0
dry=0
budget=""
real=()
scaling=""
while [[ $# -gt 0 ]]; do
    case "$1" in
        --quick) quick=1 ;;
        --dry-run) dry=1 ;;
        --wheels) shift; wheels="${1:?--wheels needs a folder}" ;;
        --budget) shift; budget="${1:?--budget needs seconds}" ;;
        --real) shift; real+=("${1:?--real needs a scene name}") ;;
        --scaling) shift; scaling="${1:?--scaling needs a number of mapping frames}" ;;
        -h|--help) sed -n '2,22p' "$0" | sed 's/^# \{0,1\}//'
                   echo "usage: $(basename "$0") [--quick] [--dry-run] [--wheels DIR] [--budget S] [--real NAME]... [--scaling FRAMES]"
                   exit 0 ;;
        *) echo "error: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
[[ -z "$budget" ]] && budget=$([[ $quick == 1 ]] && echo 900 || echo 570)
[[ "$budget" =~ ^[0-9]+$ && "$budget" -gt 0 ]] || { echo "error: --budget must be whole seconds > 0, got '$budget'" >&2; exit 2; }
[[ -z "$scaling" || ( "$scaling" =~ ^[0-9]+$ && $((scaling % 2)) == 0 && "$scaling" -ge 4 ) ]] \
    || { echo "error: --scaling takes an even number of mapping frames >= 4, got '$scaling'" >&2; exit 2; }
for name in "${real[@]}"; do
    [[ "$name" =~ ^[A-Za-z0-9_-]+$ ]] || { echo "error: --real takes a scene name, got '$name'" >&2; exit 2; }
    [[ -f "$REPO/conf/scene/$name.yaml" ]] || { echo "error: --real $name: no conf/scene/$name.yaml" >&2; exit 2; }
    if [[ $dry == 0 && ! -d "$REPO/data/raw/$name" ]]; then
        echo "error: --real $name: its photos are not in data/raw/$name (bash scripts/copy_shared_scene.sh $name, then carry data/raw/$name)" >&2
        exit 2
    fi
done
python="${PYTHON:-python}"
out="${OUT:-$REPO/results/device}"
work="${USVC_DEVICE_WORK:-${TMPDIR:-/tmp}/usvc-device-work}"

# name, time limit (s), command: the order is the order of importance
steps=()
add() { steps+=("$1|$2|${*:3}"); }
cuda_tests="$(grep -lE 'pytest\.mark\.cuda' "$REPO"/tests/test_*.py | sed "s|$REPO/||" | tr '\n' ' ')"
if [[ -n "$scaling" ]]; then  # the scaling figure alone: every stage of the room at that size, on the device
    add "scaling_$scaling" "$budget" "$python -m benchmarks.pipeline scaling --frames $scaling --threads $(nproc) --variant device_$scaling -- device=auto"
elif [[ $quick == 1 ]]; then
    add pytest_cuda 120 "$python -m pytest -q -p no:cacheprovider -m cuda $cuda_tests"
    add pipeline 380 "$python -m benchmarks.pipeline device --device auto --work $work --no-repeat --batch-sizes 2048 --head-iterations 10 --profile-iterations 5 -- train.iterations=30"
    add query 120 "$python -m benchmarks.query speed --scene-dir $work/mini/data/mini --size 640x480 --refine features none --warmup 1 --device auto"
    add folder 120 "$python -m benchmarks.query folder --scene-dir $work/mini/data/mini --workers 1 2 --repeat 1 --rounds 1 --device auto --processes"
    add serve 40 "$python -m benchmarks.query serve-load --scene-dir $work/mini/data/mini --size 640x480 --clients 1 4 --workers 4 --batch 4 --requests 20 --device auto"
    add profile_8192 120 "$python -m benchmarks.train profile --scene mini --data $work/mini/data --device auto --iterations 5 -- train.batch_size=8192 train.bundle_groups_per_batch=256"
else
    add pytest_cuda 90 "$python -m pytest -q -p no:cacheprovider -m cuda $cuda_tests"
    add pipeline 240 "$python -m benchmarks.pipeline device --device auto --work $work --batch-sizes 2048 8192"
    add query 50 "$python -m benchmarks.query speed --scene-dir $work/mini/data/mini --size 640x480 --refine features none --device auto"
    add folder 90 "$python -m benchmarks.query folder --scene-dir $work/mini/data/mini --workers 1 16 --repeat 5 --rounds 1 --device auto --processes"
    add serve 60 "$python -m benchmarks.query serve-load --scene-dir $work/mini/data/mini --size 640x480 --clients 1 16 --workers 16 --batch 16 --requests 300 --device auto"
    add profile_8192 40 "$python -m benchmarks.train profile --scene mini --data $work/mini/data --device auto --variant batch8192 -- train.batch_size=8192 train.bundle_groups_per_batch=256"
fi
# A real scene from its photos, every stage as `dvc repro` runs it (the training target's second
# scene), with what is left of the budget: last, so that it never takes the others' time.
for name in "${real[@]}"; do
    if [[ $quick == 1 ]]; then
        add "real_$name" 400 "$python -m benchmarks.pipeline device --device auto --scene $name --work $work --from prepare --no-repeat --batch-sizes --profile-iterations 0 -- train.iterations=30"
    else
        add "real_$name" 300 "$python -m benchmarks.pipeline device --device auto --scene $name --work $work --from prepare --no-repeat --batch-sizes --profile-iterations 0"
    fi
done

if [[ $dry == 1 ]]; then
    for s in "${steps[@]}"; do IFS='|' read -r name limit cmd <<< "$s"; echo "$name ($limit s): $cmd"; done
    echo "budget $budget s"
    exit 0
fi

mkdir -p "$out/benchmarks" "$out/logs"
: > "$out/steps.txt"
export USVC_BENCHMARK_DIR="$out/benchmarks"
if [[ -d "$wheels" ]]; then
    if compgen -G "$wheels/*.whl" > /dev/null; then
        "$python" -m pip install --quiet --no-index --no-deps "$wheels"/*.whl > "$out/logs/install.log" 2>&1 \
            || echo "install of $wheels/*.whl failed: see logs/install.log" | tee -a "$out/steps.txt"
    fi
    [[ -d "$wheels/src" ]] && export PYTHONPATH="$wheels/src${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
cd "$REPO" || exit 1

{
    command -v nvidia-smi > /dev/null && nvidia-smi -L
    nproc
    "$python" - <<'PY'
import importlib, platform
import torch
print("python", platform.python_version(), "torch", torch.__version__, "cuda", torch.version.cuda,
      "available", torch.cuda.is_available())
if torch.cuda.is_available():
    print("device", torch.cuda.get_device_name(0), "bf16", torch.cuda.is_bf16_supported())
missing = []
for module in ("numpy", "scipy", "cv2", "h5py", "pycolmap", "poselib", "hydra", "omegaconf", "plyfile",
               "pytorch_msssim", "tqdm", "threadpoolctl", "yaml", "PIL", "matplotlib"):
    try:
        m = importlib.import_module(module)
        print(module, getattr(m, "__version__", ""))
    except Exception as exc:  # noqa: BLE001  (what is missing, named, and the run goes on)
        missing.append(f"{module} ({exc})")
if missing:
    print("MISSING:", "; ".join(missing))
import pycolmap
print("pycolmap cuda", getattr(pycolmap, "has_cuda", "?"))
PY
} > "$out/device.txt" 2>&1
cat "$out/device.txt"

began=0  # the budget counts from the script's start: the install and device.txt are in it
for s in "${steps[@]}"; do
    IFS='|' read -r name limit cmd <<< "$s"
    left=$((budget - (SECONDS - began)))
    if (( left < 5 )); then
        echo "$name: skipped, ${left} s left of the $budget s budget" | tee -a "$out/steps.txt"
        continue
    fi
    (( left < limit )) && limit=$left
    start=$SECONDS
    # shellcheck disable=SC2086  (the command is a word list on purpose)
    timeout "$limit" $cmd > "$out/logs/$name.log" 2>&1
    rc=$?
    line="$name: exit $rc in $((SECONDS - start)) s (limit $limit s)"
    [[ $rc == 124 ]] && line="$line, cut off"
    echo "$line" | tee -a "$out/steps.txt"
    tail -n 3 "$out/logs/$name.log"
done
ls "$out/benchmarks"
