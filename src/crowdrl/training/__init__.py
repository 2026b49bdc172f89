"""D3QN training: config schema, n-step replay, trainer, checkpoints, run pipeline."""

from crowdrl.training.checkpoint import CheckpointError, load_checkpoint, load_trained_network, save_checkpoint
from crowdrl.training.config import ConfigError, RunConfig
from crowdrl.training.nstep import NStepReturn, nstep_transitions
from crowdrl.training.pipeline import evaluate_best, evaluate_network, load_agent, run_training
from crowdrl.training.trainer import Trainer
from crowdrl.training.validation import validate

__all__ = ["CheckpointError", "ConfigError", "NStepReturn", "RunConfig", "Trainer", "evaluate_best", "evaluate_network",
           "load_agent", "load_trained_network",
           "load_checkpoint", "nstep_transitions", "run_training", "save_checkpoint", "validate"]
