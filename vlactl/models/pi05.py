"""π0.5 (LeRobot's `PI05Policy`, e.g. `lerobot/pi05_libero`) behind the VLA interface:
`model=pi05 model.checkpoint=<folder or hub id>`.

Layers: `backbone.i` are PaliGemma's Gemma decoder layers, `expert.i` the Gemma action expert's. At inference
LeRobot runs the prefix through PaliGemma's language model and each denoising step through `gemma_expert.model`,
calling the decoder layers' own forwards, so plain forward hooks see their outputs (training instead runs the layers
by hand; vlactl never trains π0.5). LeRobot 0.4.4's π0.5 needs the Gemma with adaptive RMSNorm of LeRobot's
transformers branch (the `pi05` extra); LeRobot 0.6 keeps this layout (docs/real-models.md).
"""

from __future__ import annotations

from torch import nn

from vlactl.models.lerobot_flow import LeRobotFlowVLA


class PI05Adapter(LeRobotFlowVLA):
    name = "pi05"
    policy_target = "lerobot.policies.pi05.modeling_pi05:PI05Policy"
    steps_field = "num_inference_steps"

    def _embedder(self) -> nn.Module:
        return self.policy.model.paligemma_with_expert

    def _stacks(self) -> dict[str, nn.ModuleList]:
        wrapper = self._embedder()
        return {"backbone": wrapper.paligemma.model.language_model.layers, "expert": wrapper.gemma_expert.model.layers}
