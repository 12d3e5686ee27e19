#!/bin/bash
# The CUDA checks and GPU benchmarks in one pass, for a machine with a GPU (~8 min on an H100; it ran in 3 min plus the recipe step, which needed more than 150 s):
#     bash benchmarks/gpu_check.sh OUT_DIR [PYTHON]           # everything
#     bash benchmarks/gpu_check.sh OUT_DIR [PYTHON] offline   # tests/test_cuda.py, then the dataset agents' updates eager
#                                                             # against captured as CUDA graphs (cudagraphs=true), ~5 min
#     bash benchmarks/gpu_check.sh OUT_DIR [PYTHON] seeds     # the captured seed batch's CUDA tests, then benchmarks/seed_batch.py
#                                                             # eager and with --cudagraphs (IQL, CQL; 1, 5, 10 seeds)
# Runs the CUDA tests (tests/test_cuda.py and the CUDA cases beside what they check),
# then benchmarks/{offline_updates,ensemble_training,env_throughput,recipe_throughput}.py
# with --device cuda. Each step has its own time limit and writes its log to OUT_DIR,
# so a step that fails or runs out of time leaves the others' results.
out=${1:?usage: gpu_check.sh OUT_DIR [PYTHON] [offline]}; py=${2:-python}; what=${3:-all}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
step() {  # step NAME SECONDS COMMAND...
    local name=$1 limit=$2; shift 2
    echo "=== $name (limit ${limit}s): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" > "$out/$name.log" 2>&1
    local rc=$?
    tail -n 30 "$out/$name.log"
    echo "=== $name: exit $rc after $((SECONDS - t0)) s"
}
step env 30 "$py" -c "import torch, torchrl, tensordict, gymnasium, mujoco; print(torch.__version__, torchrl.__version__, tensordict.__version__, gymnasium.__version__, mujoco.__version__); print(torch.cuda.get_device_name(), torch.cuda.get_device_properties(0).total_memory // 2**30, 'GiB')"
if [ "$what" = seeds ]; then  # seeds as a batch dimension (issue 38): the captured seed batch's tests, then eager against captured
    step tests 150 "$py" -m pytest -q -p no:cacheprovider -n 4 tests/test_cuda.py -k "captured"
    step seed_batch_eager 150 "$py" benchmarks/seed_batch.py --device cuda --algos iql cql --seeds 1 5 10 --threads 1 --updates 50
    step seed_batch_captured 200 "$py" benchmarks/seed_batch.py --device cuda --cudagraphs --algos iql cql --seeds 1 5 10 --threads 1 --updates 200
    exit 0
fi
if [ "$what" = offline ]; then
    step tests 150 "$py" -m pytest -q -p no:cacheprovider -n 8 tests/test_cuda.py
    step offline_updates 330 "$py" benchmarks/offline_updates.py --device cuda --updates 500 --algos cql iql td3bc bc \
        --variants after captured "captured, sampled" captured+compiled
    exit 0
fi
step tests 110 "$py" -m pytest -q -p no:cacheprovider -n 6 tests/test_cuda.py tests/test_envs.py::test_cuda \
    tests/test_behaviour.py::test_train_and_resume_on_cuda tests/test_data.py::test_to_replay_buffer_on_cuda \
    tests/test_data.py::test_dataset_to_device_keeps_metadata_and_values
step offline_updates 200 "$py" benchmarks/offline_updates.py --device cuda --updates 200
step ensemble_training 40 "$py" benchmarks/ensemble_training.py --device cuda
step env_throughput 60 "$py" benchmarks/env_throughput.py --device cuda --batches 64 1024 4096 16384 --real-batches 64 --min-transitions 20000
step recipe_throughput 300 "$py" benchmarks/recipe_throughput.py --device cuda
