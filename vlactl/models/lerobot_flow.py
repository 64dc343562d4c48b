"""LeRobot's flow-matching VLAs (SmolVLA, π0.5) behind the VLA interface: what the two adapters share.

Both run a VLM backbone once per re-plan over the prefix [image tokens, text tokens, (state token)], then an action
expert over the chunk's tokens at every denoising step, attending to the backbone's per-layer keys/values. The
adapter keeps LeRobot's own policy class and its saved pre/post-processor pipelines (normalisation, tokenisation,
device) and adds only what the interface needs: layer names, the read-out masks of the forward that is running, and
LIBERO observations -> the policy's batch. Those masks come from wrapping the policy's own `embed_prefix` /
`embed_suffix` (and `embed_image`, to count image tokens), so they follow whatever prefix the checkpoint builds.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from vlactl.errors import UsageError
from vlactl.models.base import POOLINGS, PolicyInput, StackedLayers, episode_noise_seed, last_true

# LIBERO's two cameras in vlactl's datasets -> LeRobot's LIBERO feature names (lerobot/envs/libero.py), in order.
CAMERA_ORDER = ("image", "wrist_image")


def prefix_masks(pad: torch.Tensor, n_image: int, n_text: int) -> dict[str, torch.Tensor]:
    """Read-out sets of a prefix laid out as [n_image image tokens, n_text text tokens, rest], padding False."""
    positions = torch.arange(pad.shape[1], device=pad.device)
    image = pad & (positions < n_image)
    text = pad & (positions >= n_image) & (positions < n_image + n_text)
    return {"prefix": pad, "last": last_true(pad), "image": image, "text": text, "action": torch.zeros_like(pad)}


def suffix_masks(pad: torch.Tensor) -> dict[str, torch.Tensor]:
    """The action expert's tokens: `prefix` means all of them (see vlactl.models.base)."""
    none = torch.zeros_like(pad)
    return {"prefix": pad, "last": last_true(pad), "image": none, "text": none, "action": pad}


class LeRobotFlowVLA(StackedLayers):
    """A LeRobot flow-matching policy; subclasses name its class, stacks and embedders."""

    policy_target = ""  # "module:Class" of the LeRobot policy
    steps_field = "num_steps"  # the config field holding the number of denoising steps
    kv_source = "backbone"  # SmolVLA's and π0.5's experts attend to each VLM layer's keys/values
    env_preset = "standard"  # LeRobot's LIBERO checkpoints were trained on LIBERO's own renders (vlactl.render_presets)

    def __init__(self, policy, preprocessor, postprocessor, cameras: dict[str, str] | None = None,
                 replan_every: int | None = None):
        self.policy = policy.eval()
        self.preprocessor, self.postprocessor = preprocessor, postprocessor
        image_keys = list(policy.config.image_features)
        self.cameras = dict(cameras or zip(CAMERA_ORDER, image_keys))
        unknown = sorted(set(self.cameras.values()) - set(image_keys))
        if unknown:
            raise UsageError(f"model.cameras maps to {unknown}; the checkpoint's cameras are {image_keys}")
        self.chunk_size = int(policy.config.chunk_size)
        self.replan_every = int(replan_every or policy.config.n_action_steps)
        self.device = next(policy.parameters()).device
        self._masks: dict[str, dict[str, torch.Tensor]] = {}
        self._record_masks()

    @classmethod
    def load(cls, checkpoint: str | None = None, device: str | None = None, cameras: dict | None = None,
             replan_every: int | None = None) -> "LeRobotFlowVLA":
        """From a LeRobot checkpoint (a local folder, or a hub id where the machine has a hub)."""
        from lerobot.policies.factory import make_pre_post_processors

        from vlactl.models.registry import _import

        if not checkpoint:
            raise UsageError(f"model={cls.name} needs model.checkpoint=<local folder or hub id>")
        policy_class = _import(cls.policy_target)
        kwargs = {} if device is None else {"device": device}
        try:
            policy = policy_class.from_pretrained(str(checkpoint), **kwargs)
        except (OSError, ValueError) as exc:
            raise UsageError(f"cannot load {cls.name} checkpoint {checkpoint!r}: {str(exc).splitlines()[0]}") from None
        device = str(next(policy.parameters()).device)
        pre, post = make_pre_post_processors(
            policy.config, pretrained_path=str(checkpoint),
            preprocessor_overrides={"device_processor": {"device": device}},
        )
        return cls(policy, pre, post, cameras, replan_every)

    # --- what a subclass names (and `_stacks`) -------------------------------------------------------------------
    def _flow(self) -> nn.Module:
        """The module with `embed_prefix`, `embed_suffix` and `sample_actions` (LeRobot's `policy.model`)."""
        return self.policy.model

    def _embedder(self) -> nn.Module:
        """The module with `embed_image` (the VLM-with-expert wrapper)."""
        raise NotImplementedError

    def _image_extra_tokens(self) -> int:
        """Special tokens the prefix adds around each image."""
        return 0

    # --- layers -------------------------------------------------------------------------------------------------
    def layer_width(self, name: str) -> int:
        return self.layer_module(name).self_attn.o_proj.out_features  # the residual width, whatever the norm

    def token_mask(self, name: str, pooling: str) -> torch.Tensor:
        if pooling not in POOLINGS:
            raise KeyError(f"unknown pooling {pooling!r}; allowed: {', '.join(POOLINGS)}")
        return self._masks[name.partition(".")[0]][pooling]

    def _record_masks(self) -> None:
        """Wrap the policy's embedders (instance attributes shadow the methods) to record each forward's masks."""
        flow, embedder = self._flow(), self._embedder()
        embed_prefix, embed_suffix, embed_image = flow.embed_prefix, flow.embed_suffix, embedder.embed_image
        image_tokens: list[int] = []

        def counted_embed_image(image):
            out = embed_image(image)
            image_tokens.append(out.shape[1] + self._image_extra_tokens())
            return out

        def recorded_embed_prefix(images, img_masks, lang_tokens, *args, **kwargs):
            image_tokens.clear()
            embs, pad, att = embed_prefix(images, img_masks, lang_tokens, *args, **kwargs)
            self._masks["backbone"] = prefix_masks(pad.bool(), sum(image_tokens), lang_tokens.shape[1])
            return embs, pad, att

        def recorded_embed_suffix(*args, **kwargs):
            out = embed_suffix(*args, **kwargs)
            self._masks["expert"] = suffix_masks(out[1].bool())
            return out

        embedder.embed_image = counted_embed_image
        flow.embed_prefix = recorded_embed_prefix
        flow.embed_suffix = recorded_embed_suffix

    # --- running ------------------------------------------------------------------------------------------------
    def _batch(self, obs: PolicyInput) -> dict:
        """LIBERO observations in LeRobot's LIBERO conventions: upright float images in [0, 1], the 8-D state."""
        batch = {
            key: torch.from_numpy(np.ascontiguousarray(obs.images[camera])).permute(0, 3, 1, 2).float() / 255.0
            for camera, key in self.cameras.items()
        }
        batch["observation.state"] = torch.from_numpy(np.asarray(obs.state, dtype=np.float32))
        batch["task"] = list(obs.instruction)
        return self.preprocessor(batch)

    @torch.no_grad()
    def predict_action_chunk(self, obs: PolicyInput) -> torch.Tensor:
        return self._libero_actions(self.policy.predict_action_chunk(self._batch(obs)))

    @torch.no_grad()
    def predict_rows(self, obs: PolicyInput, states: list) -> tuple[torch.Tensor, list]:
        """A policy server's batch in one forward: row i's initial noise drawn from `states[i]` as a batch of one
        draws it (the flow's own `sample_noise`, the first draw of a prediction), all rows' noise then given to
        LeRobot's sampler together (`noise=`, which SmolVLA and π0.5 take)."""
        shape = (1, self.chunk_size, int(self.policy.config.max_action_dim))
        noise, after = [], []
        for state in states:
            self.set_sampling_state(state)
            noise.append(self._flow().sample_noise(shape, self.device))
            after.append(self.sampling_state())
        actions = self.policy.predict_action_chunk(self._batch(obs), noise=torch.cat(noise))
        return self._libero_actions(actions), after

    def _libero_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """LeRobot's chunk in LIBERO's 7-D action space, on the CPU."""
        return self.postprocessor(actions)[..., :7].float().cpu()

    @torch.no_grad()
    def encode(self, obs: PolicyInput) -> None:
        """The prefix, then one expert pass at t = 1 from a fixed noise, so expert readings are reproducible."""
        config = self.policy.config
        steps = getattr(config, self.steps_field)
        setattr(config, self.steps_field, 1)
        try:
            with torch.random.fork_rng(devices=[] if self.device.type == "cpu" else [self.device]):
                torch.manual_seed(0)
                self.policy.predict_action_chunk(self._batch(obs))
        finally:
            setattr(config, self.steps_field, steps)

    def reset(self, seed: int | None = None) -> None:
        self.policy.reset()
        if seed is not None:  # LeRobot draws its noise from torch's global generators
            torch.manual_seed(episode_noise_seed(0, seed))

    def eval(self) -> "LeRobotFlowVLA":
        self.policy.eval()
        return self
