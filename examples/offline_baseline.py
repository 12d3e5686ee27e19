"""Model-free offline RL on the dataset itself (IQL, CQL, TD3+BC, BC): the steps of ``offhrl train``, in order.

    python examples/offline_baseline.py algo=iql env=hopper dataset=medium
    python examples/offline_baseline.py algo=td3bc env=halfcheetah dataset=medium train.total_updates=100000
    python examples/offline_baseline.py algo=bc dataset=/data/hopper_medium.hdf5 seed=1

config -> data -> agent -> minibatches of the dataset -> update -> evaluate -> log / checkpoint -> report.
No world model and no CVAE: these are the peers the offline hierarchical agents are compared with, trained on the same
data and evaluated the same way (real env, deterministic, the same episodes and seeds as `offhrl train algo=moc`). The
budget counts gradient steps (train.total_updates, eval.every_updates). Outputs go to
outputs/runs/<algo>-<env>-<dataset>-seed<seed>/; running the same command again resumes.

The loop is the repository's one, :class:`torchrl_offhrl.recipes.loop.TrainingLoop`, run as ``offhrl train`` runs it;
where the pieces live: the dataset's minibatches ``recipes.loop.dataset_batches``, the agents
``torchrl_offhrl.agents`` (iql.py, cql.py, td3bc.py, bc.py: TorchRL's losses), the evaluation
``recipes.evaluation.Evaluator`` (put together by ``recipes.train.build_setting``).
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
    cfg = to_plain(cfg)
    if not learns_from_dataset(cfg):  # this script is the dataset agents' recipe; the others train on the model env
        raise SystemExit(f"algo={algo_label(cfg['algo'])} trains on the model env: run examples/offline_train.py or "
                         f"`offhrl train algo={cfg['algo']['name']} ...` (the same overrides)")
    rc = RunConfig.parse(cfg)  # every bad value named before any data work
    t_start = time.time()
    run = run_directory(cfg)
    with run.locked():
        prepared = PreparedRun.prepare(cfg, run, t_start, progress=True, rc=rc)  # data -> agent -> evaluator; resumed
        for phase in prepared.setting.phases:  # minibatches of the dataset -> agent.update -> evaluate every eval.every_updates
            prepared.loop.run_phase(phase)
        summary = prepared.finish()  # the report: summary.json, learning_curve.png
    print("\n" + format_summary(summary))
    return summary


if __name__ == "__main__":
    main()
