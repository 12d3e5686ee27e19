#!/bin/bash
# Full-scale offline runs on a lent GPU machine, from an action pack, one process per seed side by side:
#     bash scripts/gpu_runs.sh OUT_DIR PYTHON SECONDS ENV ALGO SEED...
# e.g. bash scripts/gpu_runs.sh $OUT python3 330 hopper cql 4 5 6
# 1. rebuilds .packs/ENV-medium.pt into the dataset cache (scripts/action_pack.py unpack: refused unless it is
#    the same data, bit for bit, as on the machines that generated it);
# 2. runs `scripts/results.py run --scale full --envs ENV --algos ALGO --seeds SEED` for each seed at once, with
#    --speed $SPEED (default: device=cuda algo.cudagraphs=true), each stopped after SECONDS;
# 3. every 20 s, and at the end, packs the run directories (checkpoints, evaluations, logs) into OUT_DIR/runs.tgz.
# A run cut short by the time limit resumes from its last checkpoint wherever runs.tgz is unpacked under
# outputs/results/full/ (`scripts/results.py run` again, on a CPU or a GPU); a finished one is archived and
# reported by `scripts/results.py report --scale full`. Run directories carried into outputs/results/full/
# resume here.
out=${1:?usage: gpu_runs.sh OUT_DIR PYTHON SECONDS ENV ALGO SEED...}; py=${2:?}; limit=${3:?}; env=${4:?}; algo=${5:?}; shift 5
seeds=("$@")
mkdir -p "$out" outputs/results/full
export PYTHONUNBUFFERED=1 TORCHRL_OFFHRL_CACHE=${TORCHRL_OFFHRL_CACHE:-/tmp/offhrl_cache}
t0=$SECONDS
"$py" scripts/action_pack.py unpack ".packs/$env-medium.pt" --workers 8 > "$out/unpack.log" 2>&1 || { tail -n 20 "$out/unpack.log"; exit 1; }
tail -n 2 "$out/unpack.log"; echo "unpacked after $((SECONDS - t0)) s"
dirs=()
for s in "${seeds[@]}"; do
    dirs+=("$algo-$env-medium-seed$s")
    timeout "$limit" "$py" scripts/results.py run --scale full --envs "$env" --algos "$algo" --seeds "$s" \
        --speed ${SPEED:-device=cuda algo.cudagraphs=true} > "$out/run-seed$s.log" 2>&1 &
done
pack() {  # the run directories as they stand (written to a temporary name, then renamed: never half a file)
    local have=()
    for d in "${dirs[@]}"; do [ -d "outputs/results/full/$d" ] && have+=("$d"); done
    [ ${#have[@]} -gt 0 ] && tar czf "$out/runs.tgz.part" -C outputs/results/full "${have[@]}" && mv "$out/runs.tgz.part" "$out/runs.tgz"
}
while [ -n "$(jobs -rp)" ]; do sleep 20; pack; done
wait
pack
for s in "${seeds[@]}"; do echo "--- seed $s"; tr '\r' '\n' < "$out/run-seed$s.log" | grep -E "real .* return|final|Error|error" | tail -n 14; done
echo "done after $((SECONDS - t0)) s"; ls -la "$out"
