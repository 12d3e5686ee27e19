"""Losses: the Multi-updates Option Critic (MOC)."""
from .option_critic import OptionCriticLoss, OptionGAE

__all__ = ["OptionCriticLoss", "OptionGAE"]
