"""Training: configuration, the Gaussian model, parameter surgery, densification strategies
(3DGS's ADC, CDC-GS and 3DGS-MCMC, as named presets), the loop, evaluation and the run folder."""

from .cdc import CDC
from .config import DataConfig, LearningRates, TrainConfig
from .mcmc import MCMC
from .model import GaussianModel
from .outputs import Run, load_run
from .presets import PRESETS
from .shard_training import ShardedTrainer
from .strategies import make_strategy
from .strategy import ADC, StepContext, Strategy
from .trainer import Trainer, TrainingDiverged

__all__ = [
    "ADC",
    "CDC",
    "MCMC",
    "PRESETS",
    "DataConfig",
    "GaussianModel",
    "LearningRates",
    "Run",
    "ShardedTrainer",
    "StepContext",
    "Strategy",
    "TrainConfig",
    "Trainer",
    "TrainingDiverged",
    "load_run",
    "make_strategy",
]
