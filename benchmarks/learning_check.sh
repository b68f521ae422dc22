#!/usr/bin/env bash
# Does a model trained on sceneforge's stores learn on houses it never saw? The
# training recipe of docs/learning.md on a 2-core CPU, in 17 minutes (measured on this project's machine; the target is 25):
#
#   benchmarks/learning_check.sh HOUSES WORKDIR
#
# renders HOUSES (a folder of houses, e.g. `sceneforge toy-houses houses --count 48 --seed 1`)
# into WORKDIR/gt.zarr, trains the depth, segmentation and overhead stages on the training
# houses of a split of whole houses (validation and test houses are never trained on; the
# split is saved in WORKDIR/gt.split.json),
# predicts the test houses into WORKDIR/pred.zarr and scores them with `sceneforge evaluate
# predictions` (WORKDIR/evaluation.json: the paper's table and, under "learning", each score
# of the model beside a trivial predictor's). The settings are the config files in
# benchmarks/learning/. A killed run starts again where it stopped: the store resumes and
# each stage continues from its checkpoint.
#
# The operating point (the least object probabilities predict keeps pixels at) is chosen on
# the run's own validation houses, where precision meets recall (predict.json).
#
# SCENEFORGE: the command to run (default: sceneforge on the PATH, else .venv/bin/sceneforge).
# RECIPE: the folder of config files (default benchmarks/learning/, the 2-core CPU recipe;
#         benchmarks/learning/gpu/ is the one-GPU recipe, see its README.md).
# RENDER_WORKERS: render's worker processes (default 2).
# AMP: --amp of the three training stages: auto, bf16, fp16 or off (default: the recipe's
#      config files, whose CPU recipe trains in bf16; with the CPU recipe on a CPU that does
#      not compute bfloat16 itself, no avx512_bf16 or amx_bf16 among /proc/cpuinfo's flags,
#      "off": PyTorch emulates bf16 there, several times slower than float32).
set -euo pipefail

if [ $# -ne 2 ]; then
    echo "usage: $0 HOUSES WORKDIR" >&2
    exit 2
fi
houses=$1
work=$2
recipe=${RECIPE:-$(cd "$(dirname "$0")" && pwd)/learning}
here=$(cd "$(dirname "$0")/.." && pwd)
sf=${SCENEFORGE:-$(command -v sceneforge || echo "$here/.venv/bin/sceneforge")}
[ -d "$houses" ] || { echo "error: $houses is not a folder of houses" >&2; exit 2; }
[ -f "$recipe/render.json" ] || { echo "error: RECIPE=$recipe holds no render.json" >&2; exit 2; }
mkdir -p "$work"
amp=()
if [ -n "${AMP:-}" ]; then
    # refused here, not at the first train after minutes of rendering (train --amp's choices)
    case "$AMP" in
        auto | bf16 | fp16 | off) amp=(--amp "$AMP") ;;
        *) echo "error: AMP=$AMP is not one of auto, bf16, fp16, off (train --amp)" >&2; exit 2 ;;
    esac
elif [ -z "${RECIPE:-}" ] && ! grep -qwE 'avx512_bf16|amx_bf16' /proc/cpuinfo 2>/dev/null; then
    amp=(--amp off)
    echo "note: this CPU does not compute bfloat16 itself; training in float32 (--amp off)" >&2
fi

timings=()
step() {  # step NAME COMMAND...: run it and keep its wall time
    local name=$1 t0
    shift
    t0=$(date +%s)
    echo "== $name: $*" >&2
    "$@"
    timings+=("$name $(( $(date +%s) - t0 )) s")
}

started=$(date +%s)
step render "$sf" render "$houses" "$work/gt.zarr" --config "$recipe/render.json" --workers "${RENDER_WORKERS:-2}"
for stage in depth seg overhead; do
    run="$work/runs/$stage"
    more=("${amp[@]}")
    [ -f "$run/checkpoint.pt" ] && more+=(--resume)
    [ "$stage" = overhead ] && more+=(--depth-run "$work/runs/depth" --seg-run "$work/runs/seg")
    step "$stage" "$sf" train "$work/gt.zarr" --config "$recipe/$stage.json" --run "$run" "${more[@]}"
done
step predict "$sf" predict "$work/runs/overhead" "$work/gt.zarr" "$work/pred.zarr" --config "$recipe/predict.json" \
    --overwrite
step evaluate "$sf" evaluate predictions "$work/pred.zarr" "$work/gt.zarr" --json "$work/evaluation.json" \
    --plot "$work/predictions.png"
echo "== times: ${timings[*]}; whole recipe $(( $(date +%s) - started )) s" >&2
