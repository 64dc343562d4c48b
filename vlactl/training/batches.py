"""Training batches: random frames, their action chunks, the model's processing steps, and augmentation.

All randomness comes from torch's global generator, whose state the trainer saves, so a resumed run draws the same
batches as an uninterrupted one.
"""

from __future__ import annotations

import numpy as np
import torch

from vlactl.data.frames import Frames
from vlactl.models.parts.processing import Processor
from vlactl.models.parts.vision import random_shift


class BatchSampler:
    def __init__(self, frames: Frames, processor: Processor, batch_size: int, shift: int):
        self.frames = frames
        self.processor = processor
        self.batch_size = batch_size
        self.shift = shift
        self.tokens, self.text_mask = processor.tokens(frames.tasks)  # the few instructions, tokenised once

    def __call__(self) -> dict[str, torch.Tensor]:
        index = np.sort(torch.randint(len(self.frames), (self.batch_size,)).numpy())  # sorted: friendlier to mmap
        actions, pad = self.frames.action_chunks(index, self.processor.config.chunk_size)
        task = torch.as_tensor(self.frames.task[index])
        images = self.processor.images(np.ascontiguousarray(self.frames.images[index]))
        return {
            "images": random_shift(images, self.shift),
            "state": self.processor.state(self.frames.state[index]),
            "tokens": self.tokens[task],
            "text_mask": self.text_mask[task],
            "actions": self.processor.actions(actions),
            "action_pad": torch.as_tensor(pad),
        }
