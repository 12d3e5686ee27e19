#!/usr/bin/env bash
# Issue-3 evidence: SAC, PPO and MOC offline on a generated hopper-medium dataset, side by side.
#   bash scripts/evidence_hopper.sh [extra hydra overrides]
# Budgets are modest (CPU): models fitted for a bounded number of steps, agents for FRAMES_* frames.
set -euo pipefail
OFFHRL=${OFFHRL:-offhrl}
COMMON=(env=hopper dataset=medium out_root=${OUT_ROOT:-outputs/evidence} torch_threads=${THREADS:-2}
        ensemble.fit.max_steps=${ENS_STEPS:-6000} cvae.fit.max_steps=${CVAE_STEPS:-4000} "$@")
$OFFHRL train algo=moc train.total_frames=${FRAMES_MOC:-409600} eval.every_frames=${EVAL_EVERY:-51200} "${COMMON[@]}"
$OFFHRL train algo=ppo train.total_frames=${FRAMES_PPO:-409600} eval.every_frames=${EVAL_EVERY:-51200} "${COMMON[@]}"
$OFFHRL train algo=sac train.total_frames=${FRAMES_SAC:-40960} eval.every_frames=${EVAL_EVERY_SAC:-10240} "${COMMON[@]}"
$OFFHRL aggregate ${OUT_ROOT:-outputs/evidence}/*-seed0 --out ${OUT_ROOT:-outputs/evidence}/report
