#!/bin/bash
# The offline agents' updates on a GPU, eager against captured as CUDA graphs (cudagraphs=true), in one short pass (~6 min on an H100):
#     bash benchmarks/gpu_offline.sh OUT_DIR [PYTHON]
# Runs tests/test_cuda.py (among them, for the dataset agents: the captured update matches the eager one, each form of an update is
# captured, a captured run resumes on the CPU), then benchmarks/offline_updates.py --device cuda. Each step has its own time limit and writes its log to OUT_DIR.
out=${1:?usage: gpu_offline.sh OUT_DIR [PYTHON]}; py=${2:-python}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
step() {  # step NAME SECONDS COMMAND...
    local name=$1 limit=$2; shift 2
    echo "=== $name (limit ${limit}s): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" > "$out/$name.log" 2>&1
    local rc=$?
    tail -n 25 "$out/$name.log"
    echo "=== $name: exit $rc after $((SECONDS - t0)) s"
}
step env 30 "$py" -c "import torch, torchrl, tensordict; print(torch.__version__, torchrl.__version__, tensordict.__version__, torch.cuda.get_device_name())"
step tests 150 "$py" -m pytest -q -p no:cacheprovider -n 8 tests/test_cuda.py
step offline_updates 330 "$py" benchmarks/offline_updates.py --device cuda --updates 500 --algos cql iql td3bc bc \
    --variants after captured "captured, sampled" captured+compiled
