"""Train SAC, PPO or MOC offline on the composed pessimistic model env; evaluate in the real env.

    python examples/offline_train.py algo=moc env=hopper dataset=medium
    python examples/offline_train.py algo=ppo env=hopper dataset=/data/hopper_medium.hdf5
    python examples/offline_train.py algo=sac env=halfcheetah dataset=medium-expert seed=1
    python examples/offline_train.py algo=moc ablation.no_cvae=true      # the paper's ablations
    python examples/offline_train.py algo=moc train.total_frames=200000 eval.every_frames=20000

Every algorithm trains on the same TransformedEnv(PessimisticModelEnv, LatentActionTransform),
built from the cached ensemble and CVAE; only the config group changes. Outputs go to
outputs/runs/<algo>-<env>-<dataset>-seed<seed>/ (CSV logs, evals.json, checkpoint.pt,
learning_curve.png, option_usage.png for MOC, summary.json); running the same command again
resumes from the checkpoint. Aggregate seeds with `offhrl aggregate outputs/runs/*`.
"""
import hydra
from omegaconf import DictConfig

from torchrl_offhrl.recipes.train import format_summary, train


@hydra.main(config_path="../configs", config_name="offline_train", version_base=None)
def main(cfg: DictConfig) -> None:
    print("\n" + format_summary(train(cfg)))


if __name__ == "__main__":
    main()
