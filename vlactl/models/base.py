"""The one interface every VLA implements, so that collection, probing and steering never branch on the model.

Vocabulary (TransformerLens-style): a *layer name* such as `backbone.7` or `expert.3` names the residual stream
after that decoder layer, i.e. the output of that layer, shape [batch, tokens, d]. Each model maps its names to
modules; `vlactl.models.hooks` reads and writes those outputs through forward hooks, at a *read-out token set*:

- `prefix`  mean over the prompt/prefix tokens (images + text + state) — the default (SPEC.md §2);
- `last`    the last prefix token;
- `image`   mean over image tokens only;
- `text`    mean over text tokens only;
- `action`  the positions that write the actions: an action expert's action tokens; for a model that writes its
            actions as decoder tokens (autoregressive), the prompt's last token and each decode step, every position
            whose output is the next action token. Its reading is the mean over those positions, one per forward.

For an action expert's layers the prefix sets are meaningless; there `prefix` means the action (suffix) tokens.
A forward pass whose tokens hold none of the set (e.g. an autoregressive decode step under `prefix`) has an
all-False mask: nothing is read and nothing is written there.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch.utils.hooks import RemovableHandle

POOLINGS = ("prefix", "last", "image", "text", "action")


def episode_noise_seed(base: int, episode: int | None) -> int:
    """The seed a model's sampling noise restarts from: its own `base` when no episode seed is given, else one mixed
    from both (NumPy's SeedSequence), so neighbouring episodes draw unrelated noise. Why per episode: with one noise
    sequence restarted in every episode, a run's episodes share their draws and its success hangs on that one
    sequence (the shipped hybrid: 86/100 with noise seed 0, 74/100 with seed 1, the same 100 episodes)."""
    if episode is None:
        return int(base)
    return int(np.random.SeedSequence([int(base), int(episode)]).generate_state(1)[0])
LayerHook = Callable[[torch.Tensor], "torch.Tensor | None"]


def last_true(mask: torch.Tensor) -> torch.Tensor:
    """Bool [B, T] with only the last True of each row of a bool [B, T] mask: the `last` read-out set."""
    last = torch.zeros_like(mask)
    last[torch.arange(mask.shape[0]), mask.shape[1] - 1 - mask.flip(1).int().argmax(1)] = True
    return last


@dataclass
class PolicyInput:
    """One or more observations, in the dataset's conventions (see docs/formats.md).

    images: {"image": uint8 [B, H, W, 3], "wrist_image": uint8 [B, H, W, 3]} upright
    state: float32 [B, 8] LIBERO state
    instruction: list of B strings
    """

    images: dict[str, np.ndarray]
    state: np.ndarray
    instruction: list[str]


class VLA(ABC):
    """A vision-language-action policy with observable and controllable layers."""

    name: str
    chunk_size: int = 1  # actions predicted per forward; a rollout executes `replan_every` of them
    replan_every: int = 1
    # Gripper commands the policy was trained on; a rollout executes the nearest one. LIBERO's gripper moves by the
    # *sign* of the command, so a regressed "hold" (0) that comes out as +-0.01 would open or close at full speed.
    # None: the command as predicted.
    gripper_levels: tuple[float, ...] | None = None
    device: torch.device = torch.device("cpu")
    # What it reads from a dataset: these PolicyInput cameras (iterated in order), square images of this side (None:
    # as stored; its own processor resizes them).
    cameras = ("image", "wrist_image")
    image_size: int | None = None

    # --- layers -------------------------------------------------------------------------------------------
    @abstractmethod
    def layer_names(self) -> list[str]:
        """Observable/controllable layers in forward order, e.g. ['backbone.0', ..., 'expert.0', ...]."""

    def steerable_layers(self) -> list[str]:
        """The layers whose output can move the actions (the ones a controller is placed on by default)."""
        return self.layer_names()

    @abstractmethod
    def layer_module(self, name: str) -> torch.nn.Module:
        """The module whose output (a tensor, or a tuple whose first item is one) is that layer's residual stream."""

    def hook_layer(self, name: str, fn: LayerHook) -> list[RemovableHandle]:
        """Call fn(hidden [B, T, d]) with the layer's output at each forward through it; a tensor fn returns replaces
        that output. Returns the hook handles. Models whose code never calls a layer's own forward (LeRobot's SmolVLA
        runs its layers' parts by hand) override this to reach the same residual stream another way."""

        def hook(module, args, output):
            new = fn(output[0] if isinstance(output, tuple) else output)
            if new is None:
                return None
            return (new, *output[1:]) if isinstance(output, tuple) else new

        return [self.layer_module(name).register_forward_hook(hook)]

    @abstractmethod
    def token_mask(self, name: str, pooling: str) -> torch.Tensor:
        """Bool [batch, tokens] of the read-out set for the forward currently running through layer `name`."""

    def layer_width(self, name: str) -> int:
        raise NotImplementedError

    def written_dimension(self) -> int | None:
        """The action dimension (0-6) of the token the forward now running writes, for a model that writes its
        actions one dimension a token (autoregressive); None where a forward writes whole actions (an action expert)
        or none."""
        return None

    # --- running ----------------------------------------------------------------------------------------
    @abstractmethod
    def predict_action_chunk(self, obs: PolicyInput) -> torch.Tensor:
        """Un-normalised actions [B, chunk_size, 7] in LIBERO's action space ([-1, 1], gripper -1 open / +1 close)."""

    @abstractmethod
    def encode(self, obs: PolicyInput) -> None:
        """Run every layer exactly once on these observations (collection and sweeps hook this).

        Hybrids run the prefix, then the action expert once at a fixed flow time; autoregressive models run the
        prompt forward (prefill) only.
        """

    def encode_actions(self, obs: PolicyInput) -> None:
        """`encode`, and where the model writes its actions as decoder tokens the decode steps that write them too,
        so that the `action` read-out set sees every position it steers in a rollout. By default `encode`: an action
        expert's tokens are in its one pass. Autoregressive models predict the chunk (one forward per token)."""
        self.encode(obs)

    def encode_for(self, obs: PolicyInput, pooling: str) -> None:
        """Run the forwards a read-out set reads: `encode_actions` for `action`, else `encode` (cheaper)."""
        (self.encode_actions if pooling == "action" else self.encode)(obs)

    def reset(self, seed: int | None = None) -> None:
        """Forget any per-episode state (action queues, caches). A model that draws noise restarts it, from
        `episode_noise_seed(<its own seed>, seed)`: given an episode's seed, each episode draws its own noise and the
        same episode the same noise in every run."""

    def sampling_state(self):
        """The state of the random numbers predictions draw (a flow model's noise), so that a prediction can be
        repeated with the same draw: a re-prediction under steering then differs from the unsteered one by the push
        alone. By default torch's global generator; a model with its own generator returns that one's."""
        return torch.random.get_rng_state()

    def set_sampling_state(self, state) -> None:
        torch.random.set_rng_state(state)

    def predict_rows(self, obs: PolicyInput, states: list) -> tuple[torch.Tensor, list]:
        """Rows of independent episodes (a policy server's batch), row i drawing from sampling state `states[i]`:
        the chunks [B, chunk_size, 7] each row gets predicted alone, and each row's state after. By default one
        forward per row; a model that draws its noise per row, or draws none, batches them."""
        chunks, after = [], []
        for i, state in enumerate(states):
            self.set_sampling_state(state)
            row = PolicyInput({k: v[i : i + 1] for k, v in obs.images.items()}, obs.state[i : i + 1],
                              obs.instruction[i : i + 1])
            chunks.append(self.predict_action_chunk(row))
            after.append(self.sampling_state())
        return torch.cat(chunks), after

    def reads_alike(self, a: str, b: str) -> bool:
        """Whether instructions `a` and `b` are the same input to the policy (then a run prompted with one stands in
        for a run prompted with the other). By default only the same words are."""
        return a == b

    def eval(self) -> "VLA":
        return self

    @property
    def needs_images(self) -> bool:
        return True


class StackedLayers(VLA):
    """Layer names over named stacks of decoder layers: `backbone.7` is `_stacks()["backbone"][7]`."""

    # A stack the action expert reads as per-layer keys/values (π0-style hybrids). Those come from each layer's input,
    # so the last layer's output feeds nothing and writing it cannot move the actions.
    kv_source: str | None = None

    def _stacks(self) -> dict[str, torch.nn.ModuleList]:
        raise NotImplementedError

    def layer_names(self) -> list[str]:
        return [f"{stack}.{i}" for stack, layers in self._stacks().items() for i in range(len(layers))]

    def steerable_layers(self) -> list[str]:
        names = self.layer_names()
        if self.kv_source is None:
            return names
        return [n for n in names if n != f"{self.kv_source}.{len(self._stacks()[self.kv_source]) - 1}"]

    def layer_module(self, name: str) -> torch.nn.Module:
        stack, _, index = name.partition(".")
        layers = self._stacks().get(stack)
        if layers is None or not index.isdigit() or int(index) >= len(layers):
            raise KeyError(f"unknown layer {name!r}; {self.name} has {', '.join(self.layer_names())}")
        return layers[int(index)]
