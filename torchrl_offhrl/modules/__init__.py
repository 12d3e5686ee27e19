"""Option-critic modules: heads, critic, and rollout-time option selection."""
from .options import (
    ObservationNormalizer,
    OptionCriticActor,
    OptionHeads,
    OptionValueNet,
    make_option_critic,
)

__all__ = ["ObservationNormalizer", "OptionCriticActor", "OptionHeads", "OptionValueNet", "make_option_critic"]
