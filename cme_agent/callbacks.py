"""Callbacks of our own, in SB3's callback framework."""

from __future__ import annotations

import pathlib

from stable_baselines3.common.callbacks import BaseCallback


class IterationCheckpoint(BaseCallback):
    """Save a resumable checkpoint (model + transition store + RNG state) at iteration boundaries.

    It hooks ``on_rollout_start``, which the agent calls at the start of each iteration's data
    acquisition, so a checkpoint always holds a whole number of iterations; the file is
    replaced atomically, so a crash leaves the previous checkpoint intact.

    :param path: the checkpoint file (overwritten each time)
    :param every: iterations between checkpoints
    :param verbose: 1 to print a line per checkpoint
    """

    def __init__(self, path: str | pathlib.Path, every: int = 1, verbose: int = 0) -> None:
        super().__init__(verbose)
        if every < 1:
            raise ValueError(f"checkpoint every={every} is invalid: must be an integer >= 1")
        self.path = pathlib.Path(path)
        self.every = every
        self._rollouts = 0

    def _on_rollout_start(self) -> None:
        if self._rollouts > 0 and self._rollouts % self.every == 0:
            self.model.save(self.path, include=["replay_buffer"])
            if self.verbose:
                print(f"checkpoint at {self.model.num_timesteps} steps: {self.path}")
        self._rollouts += 1

    def _on_step(self) -> bool:
        return True
