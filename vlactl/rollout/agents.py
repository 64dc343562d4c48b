"""What acts in a rollout: a VLA behind its chunked-action interface, or the privileged scripted expert.

Both give the episode loop the same two calls, `reset(env, obs)` and `act(obs) -> (7,) action`, so the loop never
branches on the model. The scripted expert needs the simulator itself (object poses), which is why an agent is reset
with the env and not just with an observation.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from vlactl.errors import UsageError

SCRIPTED = "scripted"


class VLAAgent:
    """Runs a `VLA`: predicts a chunk, executes its first `replan_every` actions, then predicts again. With
    `snap_gripper`, each gripper command becomes the nearest of the policy's `gripper_levels` (if it declares any).
    With `ensemble` (ACT's temporal ensembling, LeRobot's `ACTTemporalEnsembler`): a chunk every step, each step
    executing the average of what every chunk still covering it predicted for it, weighted exp(-ensemble * i) from
    the oldest (i = 0)."""

    def __init__(self, vla, replan_every: int | None = None, snap_gripper: bool = True,
                 ensemble: float | None = None):
        self.vla = vla.eval()
        self.chunk_size = int(vla.chunk_size)
        if ensemble is not None and replan_every not in (None, 1):
            raise UsageError(f"ensemble={ensemble} predicts a chunk every step; drop replan_every={replan_every}")
        self.replan_every = 1 if ensemble is not None else int(replan_every or vla.replan_every)
        if not 1 <= self.replan_every <= self.chunk_size:
            raise UsageError(
                f"replan_every must be in 1..{self.chunk_size} (the model's chunk size), got {self.replan_every}"
            )
        self._ensembler = None
        if ensemble is not None:
            from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

            self._ensembler = ACTTemporalEnsembler(float(ensemble), self.chunk_size)
        self.needs_images = bool(vla.needs_images)
        levels = vla.gripper_levels if snap_gripper else None
        self.gripper_levels = np.asarray(levels) if levels else None
        self._queue: list[np.ndarray] = []
        self._instruction = ""

    def reset(self, env, obs, seed: int | None = None) -> None:
        """`seed`: the episode's, from which the model's sampling noise restarts (`VLA.reset`)."""
        self.vla.reset(seed)
        self._queue = []
        self._instruction = env.instruction
        if self._ensembler is not None:
            self._ensembler.reset()

    def act(self, obs) -> np.ndarray:
        if self._ensembler is not None:
            import torch

            chunk = torch.as_tensor(self.predict(obs, self.chunk_size))[None]
            return self.snap(self._ensembler.update(chunk).numpy())[0]
        if not self._queue:
            self._queue = list(self.snap(self.predict(obs)))
        return self._queue.pop(0)

    def predict(self, obs, actions: int | None = None) -> np.ndarray:
        """The next `actions` (default `replan_every`) actions [k, 7] as the model predicts them (gripper not
        snapped)."""
        import torch

        from vlactl.models.base import PolicyInput

        batch = PolicyInput(
            images={key: img[None] for key, img in obs.images.items()},
            state=obs.libero_state[None].astype(np.float32),
            instruction=[self._instruction],
        )
        with torch.inference_mode():
            chunk = self.vla.predict_action_chunk(batch)
        return chunk[0, : actions or self.replan_every].float().cpu().numpy()

    def snap(self, actions: np.ndarray) -> np.ndarray:
        if self.gripper_levels is not None:
            nearest = np.abs(actions[:, -1:] - self.gripper_levels).argmin(-1)
            actions[:, -1] = self.gripper_levels[nearest]
        return actions


class ScriptedAgent:
    """The scripted expert with privileged object poses: an upper bound and a pipeline check, not a VLA."""

    needs_images = False
    chunk_size = replan_every = 1
    gripper_levels = None  # its commands are exact

    def __init__(self):
        from vlactl.expert.scripted import ScriptedExpert

        self.expert = ScriptedExpert()

    def reset(self, env, obs, seed: int | None = None) -> None:
        self.expert.reset(env, obs)

    def act(self, obs) -> np.ndarray:
        return self.expert.act(obs)


def load_agent(
    model: str, replan_every: int | None = None, load_policy: Callable | None = None, snap_gripper: bool = True,
    ensemble: float | None = None,
):
    """`scripted`, or a registry name / checkpoint path resolved by `load_policy` (the model registry by default)."""
    if model == SCRIPTED:
        return ScriptedAgent()
    if load_policy is None:
        from vlactl.models.registry import load_policy
    try:
        policy = load_policy(model)
    except UsageError as exc:  # the registry lists its own models; a rollout also takes the expert
        raise UsageError(f"{exc}, or {SCRIPTED}" if str(exc).startswith("unknown model") else str(exc)) from None
    return VLAAgent(policy, replan_every, snap_gripper, ensemble)
