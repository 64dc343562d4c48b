"""π0.5 (LeRobot's `PI05Policy`, e.g. `lerobot/pi05_libero`) behind the VLA interface:
`model=pi05 model.checkpoint=<folder or hub id>`.

Layers: `backbone.i` are PaliGemma's Gemma decoder layers, `expert.i` the Gemma action expert's. At inference
LeRobot runs the prefix through PaliGemma's language model and each denoising step through `gemma_expert.model`,
calling the decoder layers' own forwards, so plain forward hooks see their outputs (training instead runs the layers
by hand; vlactl never trains π0.5). LeRobot 0.4.4's π0.5 needs the Gemma with adaptive RMSNorm of openpi's
transformers branch (PyPI's transformers-openpi, the `pi05` extra); LeRobot 0.6 keeps this layout
(docs/real-models.md).
"""

from __future__ import annotations

import inspect

from torch import nn

from vlactl.errors import UsageError
from vlactl.models.lerobot_flow import LeRobotFlowVLA

OPENPI_TRANSFORMERS = "transformers-openpi==4.53.3"


def openpi_transformers_installed() -> bool:
    """Whether the `transformers` imported is openpi's branch: its GemmaRMSNorm takes `cond_dim`. (LeRobot checks the
    version only, which stock 4.53.3 shares: pip may install stock transformers' files over the branch's.)"""
    from transformers.models.gemma.modeling_gemma import GemmaRMSNorm

    return "cond_dim" in inspect.signature(GemmaRMSNorm).parameters


class PI05Adapter(LeRobotFlowVLA):
    name = "pi05"
    policy_target = "lerobot.policies.pi05.modeling_pi05:PI05Policy"
    steps_field = "num_inference_steps"

    @classmethod
    def load(cls, checkpoint: str | None = None, *args, **kwargs) -> "PI05Adapter":
        if checkpoint and not openpi_transformers_installed():
            raise UsageError(f"model=pi05 needs openpi's transformers branch (π0.5's adaptive RMSNorm): pip install "
                             f"--no-deps --force-reinstall {OPENPI_TRANSFORMERS} (docs/real-models.md)")
        return super().load(checkpoint, *args, **kwargs)

    def _embedder(self) -> nn.Module:
        return self.policy.model.paligemma_with_expert

    def _stacks(self) -> dict[str, nn.ModuleList]:
        wrapper = self._embedder()
        return {"backbone": wrapper.paligemma.model.language_model.layers, "expert": wrapper.gemma_expert.model.layers}
