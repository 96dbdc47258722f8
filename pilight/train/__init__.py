"""Shared diffusion training loop (accelerate + dvclive + safetensors checkpoints) for both stages."""

from pilight.train.checkpoint import latest_checkpoint
from pilight.train.loop import Task, train

__all__ = ["Task", "latest_checkpoint", "train"]
