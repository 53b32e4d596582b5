"""Trainer, metrics and checkpoints."""

from mpsim.training.trainer import Trainer as Trainer
