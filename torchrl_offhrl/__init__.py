"""torchrl_offhrl: offline hierarchical reinforcement learning as TorchRL components."""
__version__ = "0.1.0"
