"""Training: configuration, the Gaussian model and its optimizer, densification strategies
(ADC / 3DGS, CDC-GS), the loop, evaluation."""

from .cdc import CDC
from .config import DataConfig, TrainConfig
from .model import GaussianModel, LearningRates
from .strategy import ADC, make_strategy
from .trainer import Trainer, TrainingDiverged

__all__ = ["ADC", "CDC", "DataConfig", "GaussianModel", "LearningRates", "TrainConfig", "Trainer", "TrainingDiverged", "make_strategy"]
