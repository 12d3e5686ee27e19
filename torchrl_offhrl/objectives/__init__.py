"""Losses: the Multi-updates Option Critic (MOC), deep intra-option Q-learning (DIOL, UOF's high level), DDPG with twin critics (UOF's low level),
and TorchRL's IQL loss with each network pass computed once."""
from .diol import DIOLLoss, uof_epsilon
from .iql import SharedPassIQLLoss
from .option_critic import OptionCriticLoss, OptionGAE
from .twin_ddpg import TwinDDPGLoss

__all__ = ["DIOLLoss", "OptionCriticLoss", "OptionGAE", "SharedPassIQLLoss", "TwinDDPGLoss", "uof_epsilon"]
