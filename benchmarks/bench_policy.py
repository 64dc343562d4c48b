"""Per-control-step inference time of the embedded models, amortised over the executed part of a chunk, with 1 and
2 torch threads; parameters and checkpoint size; the cost of capturing every layer, and of capturing every layer
while the controller steers one layer (always active); one training step. Then, on the shipped hybrid
(data/policies/hybrid) with its shipped steering probes, a rollout re-plan under two constraints at once
(`constraint=[height=high,speed=low]`, control with box=action, the run's own layers and holds) against a plain one:
where both bounds hold (no push: target <= 1.05x) and where both break (the search's passes, and their cost; the
hand 1 cm below its start height, the speed bound at 80% of the predicted speed).

    python benchmarks/bench_policy.py [--checkpoint PATH ...] [--repeats 20] [--batch 32] [--no-constraints]

Without checkpoints it times freshly built default-size models (timing does not depend on the weights).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch

from vlactl.models.hooks import capture
from vlactl.models.registry import MODELS, load_policy, policy_class
from vlactl.models.parts.policy import WEIGHTS_FILE
from vlactl.steering.probes import REGRESSION, Probe
from vlactl.steering.steer import Constraint, Steerer

INSTRUCTION = "pick up the black bowl between the plate and the ramekin and place it on the plate"


def default_policy(name: str, **overrides):
    cls = policy_class(name)
    config = cls.config_class(**overrides)
    rng = np.random.default_rng(0)
    processor = cls.processor_class.fit(config, [INSTRUCTION], rng.normal(size=(100, 8)), rng.uniform(-1, 1, (100, 7)))
    return cls(config, processor).eval()


def observation(config):
    from vlactl.models.base import PolicyInput

    rng = np.random.default_rng(0)
    size = config.image_size
    images = {cam: rng.integers(0, 256, (1, size, size, 3), dtype=np.uint8) for cam in config.cameras}
    return PolicyInput(images, rng.normal(size=(1, 8)).astype(np.float32), [INSTRUCTION])


OVERHEADS = {  # variant -> the workload it is compared with
    "encode + capture all": "encode",
    "step + control": "step",
    "step + capture all + control": "step",
}


def observed_steps(policy, obs, sync=lambda: None) -> dict:
    """The workloads the overhead targets are about, each a callable to time:
    - `encode` / `encode + capture all`: the collection forward, plain and with every layer captured (issue: <= 1.10x);
    - `step` / `step + control`: a policy step, plain and with the minimal controller at the second layer, logging the
      probe reading before and after as a constrained rollout does (<= 1.05x). Its box lies beyond every reading, so
      it acts at every forward;
    - `step + capture all + control`: the worst case, every layer captured at every forward as well."""
    layer = policy.layer_names()[1]
    width = policy.layer_width(layer)
    probe = Probe(feature="z", kind=REGRESSION, layer=layer, model=policy.name, pooling="prefix",
                  weight=torch.randn(width, dtype=torch.float64), bias=0.0, mean=torch.zeros(width),
                  std=torch.ones(width))
    layers = policy.layer_names()

    def run(forward, capturing: bool, steering: bool):
        def timed():
            with capture(policy, layers if capturing else []), \
                    Steerer(policy, [Constraint(probe, 1e4, float("inf"))]) if steering else nullcontext():
                forward(obs)
            sync()
        return timed

    return {
        "encode": run(policy.encode, False, False),
        "encode + capture all": run(policy.encode, True, False),
        "step": run(policy.predict_action_chunk, False, False),
        "step + control": run(policy.predict_action_chunk, False, True),
        "step + capture all + control": run(policy.predict_action_chunk, True, True),
    }


def time_ms(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds. On a busy machine the CPU time of a 1-thread run is the better estimate of
    its wall time on a quiet one."""
    for _ in range(3):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return 1000 * float(np.median(wall)), 1000 * float(np.median(cpu))


def overheads(steps: dict, pairs: dict[str, str], repeats: int, clock=time.process_time) -> dict[str, float]:
    """Median over rounds of time(variant) / time(base) for each variant -> base of `pairs`, every workload run once
    per round in turn: on a shared VM the speed drifts by tens of percent within a minute, which timing each
    workload in its own block turns into fake overheads; paired within a round, the drift cancels."""
    names = sorted(set(pairs) | set(pairs.values()))
    for name in names:
        steps[name]()
    ratios = {variant: [] for variant in pairs}
    for r in range(repeats):
        spent = {}
        for name in names[r % len(names):] + names[:r % len(names)]:  # rotate who goes first
            start = clock()
            steps[name]()
            spent[name] = clock() - start
        for variant, base in pairs.items():
            ratios[variant].append(spent[variant] / spent[base])
    return {variant: float(np.median(r)) for variant, r in ratios.items()}


def train_step_s(policy, batch_size: int, repeats: int = 3) -> float:
    from vlactl.models.parts.vision import random_shift

    cfg = policy.config
    processor = policy.processor
    b = batch_size
    images = torch.randint(0, 256, (b, len(cfg.cameras), cfg.image_size, cfg.image_size, 3), dtype=torch.uint8)
    tokens, mask = processor.tokens([INSTRUCTION] * b)
    batch = {
        "images": random_shift(processor.images(images), 6),
        "state": torch.randn(b, cfg.state_dim),
        "tokens": tokens,
        "text_mask": mask,
        "actions": processor.actions(torch.rand(b, cfg.chunk_size, cfg.action_dim) * 2 - 1),
        "action_pad": torch.zeros(b, cfg.chunk_size, dtype=torch.bool),
    }
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    policy.train()

    def step():
        loss, _ = policy(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    torch.set_num_threads(1)
    _, cpu_ms = time_ms(step, repeats)
    policy.eval()
    return cpu_ms / 1000


def two_constraint_steps(repeats: int) -> None:
    """A re-plan of the shipped hybrid as a rollout makes it (`VLAAgent.act` with an empty queue: one chunk
    predicted) against the same re-plan by the `ConstrainedAgent` of `constraint=[height=high,speed=low]`
    (box=action): with the hand far above its start height and a huge speed threshold (both bounds hold: one
    prediction, no push), and with the hand 1 cm below its start height and a speed bound at 80% of the predicted
    speed (both break: each searched in turn, the other's probes held)."""
    from dataclasses import replace
    from types import SimpleNamespace

    from vlactl.config import REPO_ROOT
    from vlactl.env.features import CONTROL_DT
    from vlactl.rollout.agents import VLAAgent
    from vlactl.rollout.constrained import ConstrainedAgent
    from vlactl.rollout.plan import steering
    from vlactl.rollout.runner import canonical_constraint, resolve_defaults, rollout_config

    if not (REPO_ROOT / "data" / "policies" / "hybrid").is_dir():
        print("two constraints: skipped, no shipped hybrid in data/policies/hybrid")
        return
    torch.set_num_threads(1)
    cfg = rollout_config(["model=hybrid", "constraint=[height=high,speed=low]", f"demos={REPO_ROOT / 'no-demos'}"])
    constraints = canonical_constraint(cfg)
    resolve_defaults(cfg)
    plan = steering(cfg, constraints)  # the rollout's probes, layers and holds (shipped probes, their constants)
    vla = load_policy("hybrid")
    rng = np.random.default_rng(0)
    size = vla.config.image_size
    images = {cam: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for cam in vla.config.cameras}
    libero_state = rng.normal(size=8).astype(np.float32)
    env = SimpleNamespace(instruction=INSTRUCTION)

    def seen(z: float):
        return SimpleNamespace(images=images, libero_state=libero_state, state=np.array([0, 0, z, 0, 0, 0, 0.04]))

    def replan(agent, z: float):
        obs = seen(z)

        def step():
            agent._queue, agent._t = [], 0  # a re-plan at the window's first step
            agent.act(obs)
        return step

    def with_threshold(threshold):
        return replace(plan, bounds=replace(plan.bounds, speed_threshold=threshold))

    hold = ConstrainedAgent(vla, constraints, with_threshold(1e3))
    hold.reset(env, seen(1.0))  # start height 1.0 m
    replan(hold, 1.2)()
    speed = hold.readings[0]["action_before_speed"]  # the unsteered commanded speed: the break case asks for 80% of it
    threshold = 0.8 * speed * plan.bounds.metres_per_unit / CONTROL_DT
    agents = {"plain": VLAAgent(vla), "bounds hold": hold,
              "bounds break": ConstrainedAgent(vla, constraints, with_threshold(threshold))}
    for agent in agents.values():
        agent.reset(env, seen(1.0))
    steps = {"plain": replan(agents["plain"], 1.0), "bounds hold": replan(agents["bounds hold"], 1.2),
             "bounds break": replan(agents["bounds break"], 0.99)}
    plain_ms, _ = time_ms(steps["plain"], repeats)
    ratio = overheads(steps, {"bounds hold": "plain", "bounds break": "plain"}, repeats)
    layers = {c.name: sorted({p.layer for p in plan.probes if p.feature in c.action_features}) for c in constraints}
    held = sorted({p.feature for p in plan.holds})
    print(f"two constraints ({constraints[0].name}, {constraints[1].name}; control, box=action) on the shipped hybrid, "
          f"steered layers {layers}, held {held}: a plain re-plan {plain_ms:.1f} ms (1 thread)")
    for name in ("bounds hold", "bounds break"):
        row = agents[name].readings[0]
        passes = row["passes"]
        quantities = ", ".join(f"{c.feature} {row[f'action_before_{c.feature}']:+.3f}->"
                               f"{row[f'action_after_{c.feature}']:+.3f} in [{row[f'bound_lo_{c.feature}']:+.3f}, "
                               f"{row[f'bound_hi_{c.feature}']:+.3f}]" for c in constraints)
        print(f"  {name:12s}: {ratio[name]:.3f}x a plain re-plan ({100 * (ratio[name] - 1):+.1f}%), "
              f"{passes} steered re-predictions; {quantities}" + ("  (target <= 1.05x)" if not passes else ""))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", nargs="*", default=[], help="checkpoint folders (default: fresh models)")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--batch", type=int, default=32, help="batch size of the timed training step (0: skip)")
    parser.add_argument("--no-constraints", action="store_true", help="skip the shipped hybrid's two-constraint step")
    args = parser.parse_args()
    policies = [load_policy(p) for p in args.checkpoint] or [default_policy(name) for name in MODELS]
    print(f"{'model':15s} {'params':>8s} {'ckpt MB':>8s} {'chunk/replan':>12s} {'ms/step 1t':>10s} {'(cpu)':>6s} "
          f"{'ms/step 2t':>10s} {'collect: capture all':>20s} {'step: control':>13s} {'step: all+control':>17s} "
          f"{'train s/step':>12s}")
    for policy in policies:
        obs = observation(policy.config)
        with tempfile.TemporaryDirectory() as tmp:
            policy.save_pretrained(Path(tmp))
            mb = (Path(tmp) / WEIGHTS_FILE).stat().st_size / 2**20
        steps = observed_steps(policy, obs)
        per_step = policy.replan_every
        torch.set_num_threads(2)
        two, _ = time_ms(steps["step"], args.repeats)
        torch.set_num_threads(1)
        one, one_cpu = time_ms(steps["step"], args.repeats)
        ratio = overheads(steps, OVERHEADS, args.repeats)
        step = train_step_s(policy, args.batch) if args.batch else float("nan")
        params = sum(p.numel() for p in policy.parameters()) / 1e6

        def extra(name):
            return f"{100 * (ratio[name] - 1):+.1f}%"

        print(f"{policy.name:15s} {params:7.2f}M {mb:8.1f} {policy.chunk_size:>6d}/{per_step:<5d} "
              f"{one / per_step:10.1f} {one_cpu / per_step:6.1f} {two / per_step:10.1f} "
              f"{extra('encode + capture all'):>20s} {extra('step + control'):>13s} "
              f"{extra('step + capture all + control'):>17s} {step:12.3f}")
    print("ms/step: one predict_action_chunk over the actions executed from it (replan_every), wall and (cpu) time, "
          f"median of {args.repeats}; overheads: median over {args.repeats} rounds (each workload once per round) of the "
          f"CPU time ratio; collect: extra CPU time of the collection forward (encode) with every layer "
          f"captured (target <= +10%); step: control = the minimal controller with its readings at "
          f"{policy.layer_names()[1]}, active at every forward (target <= +5%); all+control: every layer captured at "
          f"every forward as well; train: CPU s per step, batch {args.batch}, 1 thread")
    if not args.no_constraints:
        two_constraint_steps(args.repeats)


if __name__ == "__main__":
    main()
