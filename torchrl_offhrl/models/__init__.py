"""Learned models: vectorised ensembles, the dynamics ensemble, the CVAE, their trainer and their held-out quality."""
from .bc import ClonedPolicy, PercentileBC
from .cvae import ConditionalVAE, CVAEDecoder, LatentOrigin
from .dynamics import DISCREPANCIES, DynamicsEnsemble, EnsembleLinear, EnsembleMLP
from .quality import decoder_sensitivity, ensemble_quality
from .trainer import SupervisedTrainer, atomic_torch_save

__all__ = [
    "CVAEDecoder",
    "ClonedPolicy",
    "ConditionalVAE",
    "DISCREPANCIES",
    "DynamicsEnsemble",
    "EnsembleLinear",
    "EnsembleMLP",
    "LatentOrigin",
    "PercentileBC",
    "SupervisedTrainer",
    "atomic_torch_save",
    "decoder_sensitivity",
    "ensemble_quality",
]
