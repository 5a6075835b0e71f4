#!/usr/bin/env bash
# The GPU figures in one short run: env throughput at B = 16384 and 65536, one update
# eager and compiled (default mode and reduce-overhead, i.e. CUDA graphs), the planner at B = 1024
# episodes, and the main job until its validation success reaches 0.95 (or a wall-time cap);
# `graphs`: the update captured whole in a CUDA graph (compile.cudagraphs), SAC-SILP+ and plain SAC.
#
#   bash benchmarks/gpu.sh [bench|main|graphs|all]   # figures land in $OUT (default gpu_out/), one file per part
#   DEVICE=cpu LIMIT_PERCENT=10 bash benchmarks/gpu.sh bench   # the script's own dry run, on the CPU
#
# Each part has its own time limit so that one slow part cannot eat the others' time; what a part
# printed before its limit stays in its file. The package runs from this checkout; where the machine's
# Python lacks its dependencies and has no index to install from, wheels put in .whl/ are installed
# to /tmp/site first.
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
PART=${1:-all}
# the package as an install lays it out (assets/ is installed as torchrl_silp.assets), without pip
rm -rf /tmp/gpu_src && mkdir -p /tmp/gpu_src && cp -r torchrl_silp /tmp/gpu_src/ && cp -r assets /tmp/gpu_src/torchrl_silp/
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/gpu_src${PYTHONPATH:+:$PYTHONPATH}
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH=$PYTHONPATH:/tmp/site
fi
PY=python3
DEVICE=${DEVICE:-cuda}
LIMIT_PERCENT=${LIMIT_PERCENT:-100}

run() {  # run NAME SECONDS CMD...: the command's output to $OUT/NAME.txt and to the log, killed after SECONDS
    local name=$1 limit=$(($2 * LIMIT_PERCENT / 100))
    shift 2
    echo "=== $name ($(date -u +%H:%M:%S), limit ${limit}s): $*" | tee -a "$OUT/log.txt"
    local start=$SECONDS
    mkdir -p /tmp/gpu_err  # stderr (compile warnings) stays out of $OUT: one small file per part there
    timeout -k 5 "$limit" "$@" >"$OUT/$name.txt" 2>"/tmp/gpu_err/$name.err"
    local rc=$?
    grep -v "Warning\|warn(\|^  \|^$" "/tmp/gpu_err/$name.err" | tail -15 >>"$OUT/$name.txt"
    cat "$OUT/$name.txt" >>"$OUT/log.txt"
    echo "=== $name: exit $rc after $((SECONDS - start)) s" | tee -a "$OUT/log.txt"
}

{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    $PY -c "import torch, torchrl, tensordict; print('torch', torch.__version__, 'torchrl', torchrl.__version__, \
'tensordict', tensordict.__version__, 'cuda', torch.cuda.is_available())"
} 2>&1 | tee -a "$OUT/log.txt"

mujoco_configs=20000
$PY -c "import mujoco" 2>/dev/null || mujoco_configs=0

if [ "$PART" = bench ] || [ "$PART" = all ]; then
    run env_throughput 120 $PY benchmarks/env_throughput.py --device $DEVICE --quick --batch-sizes 16384 65536 \
        --mujoco-configs $mujoco_configs
    run update_step 100 $PY benchmarks/update_step.py --reps 30 device=$DEVICE
    run update_step_cudagraphs 70 $PY benchmarks/update_step.py --reps 30 device=$DEVICE \
        compile.compile_mode=reduce-overhead
    run planner 60 $PY benchmarks/planner.py --device $DEVICE --quick --batch-sizes 1024 --sweep-batch 1024 \
        --rollouts scripted --d-values 0.15
fi
if [ "$PART" = graphs ] || [ "$PART" = all ]; then
    run update_step_graphed 100 $PY benchmarks/update_step.py --reps 30 device=$DEVICE \
        compile.cudagraphs=true silp.demo_rows=mask
    run update_step_graphed_sac 60 $PY benchmarks/update_step.py --reps 30 device=$DEVICE \
        compile.cudagraphs=true method=sac
fi
if [ "$PART" = main ] || [ "$PART" = all ]; then
    run time_to_success 250 $PY benchmarks/time_to_success.py --seed 0 device=$DEVICE max_train_wall_s=180
fi
