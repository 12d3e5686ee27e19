#!/bin/bash
# Full-scale offline runs on a lent GPU machine, from an action pack, one process per seed side by side:
#     bash scripts/gpu_runs.sh OUT_DIR PYTHON SECONDS ENV[,ENV...] ALGO SEED...
# e.g. bash scripts/gpu_runs.sh $OUT python3 430 hopper,halfcheetah cql 4 5 6
# 1. rebuilds each .packs/ENV-medium.pt into the dataset cache (scripts/action_pack.py unpack: refused unless it is
#    the same data, bit for bit, as on the machines that generated it), the envs side by side;
# 2. as soon as an env's data is there, runs `python -m torchrl_offhrl.cli results table1 run --scale full --envs ENV --algos ALGO --seeds SEED`
#    for each seed at once, with --speed $SPEED (default: device=cuda algo.cudagraphs=true); every run is stopped
#    SECONDS after the script started.
# DATASET=medium-expert (default medium) trains on medium-expert, rebuilt from the packs of its two parts
# (.packs/ENV-medium.pt and .packs/ENV-expert.pt: `python scripts/action_pack.py pack hopper-expert .packs/hopper-expert.pt`).
# A pack that was not carried is skipped, its dataset taken from the cache an earlier call on the same (warm) machine
# rebuilt; UNPACK_ONLY=1 stops after rebuilding. HalfCheetah's medium-expert (two packs, 36 MiB, too much beside the
# wheels): call 1 carries .whl and .packs/halfcheetah-medium.pt with UNPACK_ONLY=1; call 2, at once (a machine idle
# for 30 s is given back), carries .packs/halfcheetah-expert.pt only and skips the pip install (/tmp/site stays).
# With BATCH=1 the seeds train as one process (`--batch-seeds`: one vmapped update for all of them, captured as CUDA graphs
# with algo.cudagraphs=true), its log run-ENV-batch.log.
# With MPS=1 in the environment it first starts CUDA's MPS daemon and checks that a process can use the GPU through
# it (if not, it quits it and the runs share the GPU by time slices: ~770 updates/s together, measured below).
# 3. every 20 s, and at the end, packs each run directory (checkpoint, evaluations, logs) into OUT_DIR/<run>.tgz.
# A run cut short by the time limit resumes from its last checkpoint wherever its .tgz is unpacked under
# outputs/results/full/ (`python -m torchrl_offhrl.cli results table1 run` again, on a CPU or a GPU); a finished one is archived and
# reported by `python -m torchrl_offhrl.cli results table1 report --scale full`. Run directories carried into outputs/results/full/
# resume here.
# Measured (2026-11-27, H100, CQL on hopper-medium, seeds 4-6, SPEED="device=cuda algo.cudagraphs=true algo.compile=true"):
# unpacking took 46 s; the three runs shared the GPU at ~770 updates/s together (each 10k-update block took 38-40 s,
# about what one process gets alone: the GPU, not Python, bounds them), and their first 10k updates took 1:45 with
# the compile and the first evaluation; 370 s took each to ~70k of 100k updates. Budget ~8.5 min for three 100k runs.
# With MPS=1 (same day, same card and SPEED; CQL on hopper-medium and halfcheetah-medium, seeds 4-6: six runs):
# ~350 updates/s each once compiled, ~2,100 together (2.7x the time slices); every run finished its 100k updates in
# about 6 min, the whole call in 471 s with the 47 s of unpacking. So: MPS=1, and six runs to a call.
# A call returns at most 8 files: six run archives and logs.tgz fit.
# What travels: carry .whl and the packs (the folder .packs, or single files such as .packs/hopper-medium.pt), 64 MiB
# in all with the repository's tracked files (23.5 MiB on 2026-12-04, 18 of them docs/results: move that folder out of
# the checkout for the call, `mv docs/results /tmp/`, and back after; the runs do not read it). Packs: hopper-medium
# 9.7 MiB, hopper-expert 9.6, halfcheetah-medium 17.6, halfcheetah-expert 18.3. .whl is 23 MiB (torchrl 0.14.1,
# tensordict 0.14.3, gymnasium 1.4.0, mujoco 3.11.0, glfw, hydra-core 1.3.8, omegaconf 2.3.1, antlr4-python3-runtime
# 4.9.3 built here with `pip wheel`, farama-notifications, orjson, pyvers, importlib_metadata; cp312 manylinux), without
# pyopengl (no run here renders); glfw (0.25 MB) must stay: Gymnasium's MuJoCo envs import it when MUJOCO_GL is unset.
# Both medium packs fit one call; medium-expert, one env a call (hopper's two packs with docs/results moved out).
# Install on the machine: python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl and
# PYTHONPATH=/tmp/site:$PWD.
out=${1:?usage: gpu_runs.sh OUT_DIR PYTHON SECONDS ENV[,ENV...] ALGO SEED...}; py=${2:?}; limit=${3:?}; envs=${4:?}; algo=${5:?}; shift 5
seeds=("$@")
dataset=${DATASET:-medium}; parts=$dataset; [ "$dataset" = medium-expert ] && parts="medium expert"
mkdir -p "$out" outputs/results/full
export PYTHONUNBUFFERED=1 TORCHRL_OFFHRL_CACHE=${TORCHRL_OFFHRL_CACHE:-/tmp/offhrl_cache}
t0=$SECONDS
if [ "${MPS:-0}" = 1 ]; then  # opt-in: CUDA MPS lets the processes' kernels run at once instead of in turns
    export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps_pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps_log
    mkdir -p /tmp/mps_pipe /tmp/mps_log
    if nvidia-cuda-mps-control -d && "$py" -c "import torch; assert torch.ones(2, device='cuda').sum().item() == 2"; then
        echo "MPS daemon started"
    else
        echo "MPS unusable here: the runs share the GPU by time slices"; echo quit | nvidia-cuda-mps-control 2>/dev/null
        unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY; MPS=0
    fi
fi
dirs=()
for env in ${envs//,/ }; do
    for s in "${seeds[@]}"; do dirs+=("$algo-$env-$dataset-seed$s"); done
    (   # each env's seeds start as soon as its own dataset is rebuilt; every run stops at the common deadline
        for part in $parts; do
            if [ ! -f ".packs/$env-$part.pt" ]; then  # not carried this call: rebuilt into the cache by an earlier call
                echo "no .packs/$env-$part.pt: using the $env-$part dataset an earlier call rebuilt into $TORCHRL_OFFHRL_CACHE"; continue
            fi
            "$py" scripts/action_pack.py unpack ".packs/$env-$part.pt" --workers 8 > "$out/unpack-$env-$part.log" 2>&1 \
                || { tail -n 20 "$out/unpack-$env-$part.log"; exit 1; }
        done
        echo "$env unpacked after $((SECONDS - t0)) s"
        [ "${UNPACK_ONLY:-0}" = 1 ] && exit 0
        if [ "${BATCH:-0}" = 1 ]; then  # the seeds as one process, one vmapped (and, with cudagraphs, captured) update
            timeout $((limit - (SECONDS - t0))) "$py" -m torchrl_offhrl.cli results table1 run --scale full --envs "$env" --algos "$algo" --seeds "${seeds[@]}" \
                --datasets "$dataset" --batch-seeds --speed ${SPEED:-device=cuda algo.cudagraphs=true} > "$out/run-$env-batch.log" 2>&1
            echo "$env: the batch exited with $? after $((SECONDS - t0)) s"
            exit 0
        fi
        for s in "${seeds[@]}"; do
            timeout $((limit - (SECONDS - t0))) "$py" -m torchrl_offhrl.cli results table1 run --scale full --envs "$env" --algos "$algo" --seeds "$s" --datasets "$dataset" \
                --speed ${SPEED:-device=cuda algo.cudagraphs=true} > "$out/run-$env-seed$s.log" 2>&1 &
        done
        wait
    ) &
done
pack() {  # each run directory as it stands, in its own OUT_DIR/<run>.tgz (16 MiB a file come back; three runs in one were 17 MB),
          # written to a temporary name and renamed: never half a file. tar's "file changed as we read it" (exit 1) is expected
    for d in "${dirs[@]}"; do
        [ -d "outputs/results/full/$d" ] || continue
        tar czf "$out/$d.tgz.part" --warning=no-file-changed -C outputs/results/full "$d"; [ $? -le 1 ] && mv "$out/$d.tgz.part" "$out/$d.tgz"
    done
}
while [ -n "$(jobs -rp)" ]; do sleep 20; pack; done
wait
pack
[ "${MPS:-0}" = 1 ] && echo quit | nvidia-cuda-mps-control 2>/dev/null
for env in ${envs//,/ }; do for s in "${seeds[@]}" batch; do
    log="$out/run-$env-seed$s.log"; [ "$s" = batch ] && log="$out/run-$env-batch.log"
    [ -f "$log" ] || continue
    echo "--- $env seed $s"; tr '\r' '\n' < "$log" | grep -E "real .* return|final|Error|error" | tail -n 14
done; done
# the logs travel as one archive: a call returns at most 8 files (six runs' archives and their eight logs lost six logs)
(cd "$out" && tar czf logs.tgz ./*.log && rm -f ./*.log)
echo "done after $((SECONDS - t0)) s"; ls -la "$out"
