"""Offline training on the pessimistic model env, for any registered agent: the steps of ``offhrl train``, in order.

The model env's three settings run through this one script (the dataset agents through examples/offline_baseline.py):

    python examples/offline_train.py algo=moc env=hopper dataset=medium
    python examples/offline_train.py algo=ppo env=hopper dataset=/data/hopper_medium.hdf5
    python examples/offline_train.py algo=sac env=halfcheetah dataset=medium-expert seed=1
    python examples/offline_train.py algo=moc ablation.no_cvae=true      # the paper's ablations
    python examples/offline_train.py algo=moc transfer.task=backward     # transfer: offline, then online on the backward task
    python examples/offline_train.py algo=uof env=blockstack2 dataset=medium-expert   # goal-conditioned block stacking

config -> data -> models -> offline rules (calibration report) -> latent origin -> composed env -> agent -> loop -> returned
policy -> report. Every algorithm trains on the same TransformedEnv(PessimisticModelEnv, LatentActionTransform); only the
`algo` config group changes (configs/algo/*.yaml, one agent file each in torchrl_offhrl/agents/). Outputs go to
outputs/runs/<algo>-<env>-<dataset>-seed<seed>/ (CSV logs, evals.json, checkpoint.pt, selected.pt, calibration.json/.png,
learning_curve.png, summary.json); running the same command again resumes from the checkpoint.

There is one training loop in the repository, :class:`torchrl_offhrl.recipes.loop.TrainingLoop`, and this script runs it
as ``offhrl train`` does (a test checks that both write the same records), so the two cannot drift apart. Where each step
lives, to read or to replace:

* data and models: ``torchrl_offhrl.recipes.config.resolve_dataset``, ``recipes.pipeline.fit_or_load_models``;
* the P-MDP's settings from the data and the models: ``torchrl_offhrl.envs.rules`` (printed as the calibration report);
* the latent origin, the composed env, the agent, its evaluators: ``recipes.pipeline.apply_latent_origin``,
  ``make_model_env``, ``torchrl_offhrl.agents.make_agent``, ``recipes.evaluation.Evaluator`` (put together by
  ``recipes.train.build_setting``);
* collect -> update -> evaluate -> checkpoint: ``recipes.loop.TrainingLoop.run_phase``;
* the returned policy (the last one unless the offline guard finds no gain over the start): ``recipes.selection``.
"""
import time

import hydra
from omegaconf import DictConfig

from torchrl_offhrl.recipes.config import algo_label, learns_from_dataset
from torchrl_offhrl.recipes.report import format_summary
from torchrl_offhrl.recipes.schema import RunConfig
from torchrl_offhrl.recipes.train import PreparedRun, run_directory
from torchrl_offhrl.utils import to_plain


@hydra.main(config_path="../configs", config_name="offline_train", version_base=None)
def main(cfg: DictConfig) -> dict:
    # config: every bad value is named here, before any data or model work
    cfg = to_plain(cfg)
    if learns_from_dataset(cfg):  # this script is the model-env recipe; iql / cql / td3bc / bc learn from the dataset itself
        raise SystemExit(f"algo={algo_label(cfg['algo'])} learns from the dataset, not from the model env: run "
                         f"`offhrl train algo={cfg['algo']['name']} ...` (the same overrides), or examples/offline_baseline.py")
    rc = RunConfig.parse(cfg)
    t_start = time.time()
    run = run_directory(cfg)  # outputs/runs/<algo>-<env>-<dataset>-seed<seed>/, locked while the run lives
    with run.locked():
        # data -> models -> offline rules -> latent origin -> env -> agent -> evaluators, and the checkpoint resumed
        prepared = PreparedRun.prepare(cfg, run, t_start, progress=True, rc=rc)
        # the loop: collect from the model env, agent.update(batch), evaluate every eval.every_frames, checkpoint
        for phase in prepared.setting.phases:
            prepared.loop.run_phase(phase)
        # the returned policy (selected.pt: the guard's verdict) and the report (summary.json, learning_curve.png)
        summary = prepared.finish()
    print("\n" + format_summary(summary))
    return summary


if __name__ == "__main__":
    main()
