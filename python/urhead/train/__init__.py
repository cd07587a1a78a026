"""Fitting an avatar to a subject: the training loop, its loss, checkpoints and plots."""

from urhead.train.trainer import FitResult, Trainer

__all__ = ["FitResult", "Trainer"]
