"""Losses: the Multi-updates Option Critic (MOC), deep intra-option Q-learning (DIOL, UOF's high level)."""
from .diol import DIOLLoss, uof_epsilon
from .option_critic import OptionCriticLoss, OptionGAE

__all__ = ["DIOLLoss", "OptionCriticLoss", "OptionGAE", "uof_epsilon"]
