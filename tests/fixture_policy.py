"""A test-only VLA: always the same chunk (rise slowly, gripper open). Lets rollouts run without a trained model."""

import torch

from vlactl.models.base import VLA

CHUNK = torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0, 0.0, -1.0]] * 4)


class FixedChunkPolicy(VLA):
    name = "fixture"
    chunk_size = 4
    replan_every = 2

    def __init__(self, needs_images: bool = False):
        self._needs_images = needs_images
        self.calls = 0

    @property
    def needs_images(self) -> bool:
        return self._needs_images

    def predict_action_chunk(self, obs):
        self.calls += 1
        return CHUNK.expand(len(obs.instruction), -1, -1).clone()

    def layer_names(self):
        return []

    def layer_module(self, name):
        raise KeyError(name)

    def token_mask(self, name, pooling):
        raise KeyError(name)

    def encode(self, obs):
        pass


def load(model: str) -> FixedChunkPolicy:
    """Stands in for the model registry; spawned workers import it by name (pytest puts tests/ on sys.path)."""
    return FixedChunkPolicy()
