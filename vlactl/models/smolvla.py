"""SmolVLA (LeRobot's `SmolVLAPolicy`) behind the VLA interface: `model=smolvla model.checkpoint=<folder or hub id>`.

Layers: `backbone.i` are the SmolVLM text decoder layers the policy keeps (`num_vlm_layers`), `expert.i` the action
expert's. SmolVLA never calls a decoder layer's own forward — `SmolVLMWithExpertModel.forward` runs each layer's
attention and MLP by hand — so a forward hook on the layer would never fire. The layer's output is
`residual + mlp(post_attention_layernorm(residual))`; we keep the residual from a pre-hook on that norm and read or
write the sum at the MLP's output, which is the same point of the residual stream.
"""

from __future__ import annotations

from torch import nn
from torch.utils.hooks import RemovableHandle

from vlactl.models.base import LayerHook
from vlactl.models.lerobot_flow import LeRobotFlowVLA


class SmolVLAAdapter(LeRobotFlowVLA):
    name = "smolvla"
    policy_target = "lerobot.policies.smolvla.modeling_smolvla:SmolVLAPolicy"

    def _embedder(self) -> nn.Module:
        return self.policy.model.vlm_with_expert

    def _stacks(self) -> dict[str, nn.ModuleList]:
        wrapper = self._embedder()
        return {"backbone": wrapper.get_vlm_model().text_model.layers, "expert": wrapper.lm_expert.layers}

    def _image_extra_tokens(self) -> int:
        return 3 if self.policy.config.add_image_special_tokens else 0  # 2 start tokens + 1 end token per image

    def hook_layer(self, name: str, fn: LayerHook) -> list[RemovableHandle]:
        layer = self.layer_module(name)
        residual = {}

        def keep_residual(module, args):
            residual["h"] = args[0]

        def at_mlp_output(module, args, output):
            hidden = residual.pop("h") + output
            new = fn(hidden)
            return None if new is None else output + (new - hidden)

        return [
            layer.post_attention_layernorm.register_forward_pre_hook(keep_residual),
            layer.mlp.register_forward_hook(at_mlp_output),
        ]
