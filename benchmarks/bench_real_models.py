"""Observer + controller overhead on real-VLA-sized models with random weights: a policy step with the minimal
controller acting at one layer (its readings logged), and the same with every layer captured, against a plain step.

    python benchmarks/bench_real_models.py [--layers N] [--repeats 5]

Models, built from the libraries' classes at the published widths (random weights; timing does not depend on them):
- `openvla-sized`: the OpenVLA adapter over a Hugging Face LLaVA with Llama-2-7B's decoder (4096 wide, 11008 MLP,
  32 heads) and a SigLIP-so400m vision tower (OpenVLA's fused DINOv2 + SigLIP is hub code); 7 greedy action tokens.
- `smolvla-sized`: LeRobot's SmolVLA over SmolVLM2-500M's text widths (960 wide, 2560 MLP, 15 heads, 5 KV heads),
  16 VLM layers kept and the 0.75-wide expert, 50-action chunks, 10 denoising steps.
π0.5 itself cannot be built without LeRobot's transformers branch (docs/real-models.md), so it is not timed.

On a GPU (bfloat16) every layer is built; on a CPU only `--layers` decoder layers (default 2) at full width, which
keeps the per-layer cost of the hooks in proportion. Prints the ratios; the goal is ≤ 1.05×.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the tiny-checkpoint writers, at full width

from bench_policy import OVERHEADS, observed_steps, overheads, time_ms  # noqa: E402
from real_model_fixtures import OPENVLA_PROMPT, write_llava, write_smolvla  # noqa: E402
from synthetic_demos import observation  # noqa: E402

from vlactl.models.registry import load_policy  # noqa: E402

LLAMA2_7B = dict(hidden_size=4096, intermediate_size=11008, num_attention_heads=32, num_key_value_heads=32)
SIGLIP_SO400M = dict(hidden_size=1152, intermediate_size=4304, num_hidden_layers=27, num_attention_heads=16,
                     image_size=224, patch_size=14)
SMOLVLM2_500M = dict(hidden_size=960, intermediate_size=2560, num_attention_heads=15, num_key_value_heads=5,
                     head_dim=64)
SMOLVLM2_VISION = dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                       image_size=512, patch_size=16)  # SigLIP-base at 512 px; pixel shuffle 4 -> 64 tokens/image


def build(name: str, folder: Path, layers: int, device: str):
    if name == "openvla-sized":
        write_llava(folder, text=dict(LLAMA2_7B, num_hidden_layers=layers), vision=SIGLIP_SO400M)
        return load_policy("openvla", checkpoint=str(folder), prompt=OPENVLA_PROMPT, append_token=None,
                           device=device, dtype="bfloat16" if device == "cuda" else "float32")
    write_smolvla(folder, text=dict(SMOLVLM2_500M, num_hidden_layers=layers), vision=SMOLVLM2_VISION, scale_factor=4,
                  chunk_size=50, steps=10, device=device)
    return load_policy("smolvla", checkpoint=str(folder))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layers", type=int, default=None, help="decoder layers (default: all on a GPU, 2 on a CPU)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    full = {"openvla-sized": 32, "smolvla-sized": 16}
    print(f"device: {device}" + ("" if device == "cuda" else " (no GPU: full width, fewer layers)"))
    print(f"{'model':14s} {'layers':>6s} {'plain ms':>9s} {'control ms':>10s} {'ratio':>6s} "
          f"{'all+control ms':>14s} {'ratio':>6s}")
    for name, depth in full.items():
        layers = args.layers or (depth if device == "cuda" else 2)
        with tempfile.TemporaryDirectory() as tmp:
            vla = build(name, Path(tmp), layers, device)
        obs = observation(1)
        steps = observed_steps(vla, obs, sync)
        with torch.inference_mode():
            plain = time_ms(steps["step"], args.repeats)[0]
            pairs = {k: v for k, v in OVERHEADS.items() if v == "step"}
            ratio = overheads(steps, pairs, args.repeats, clock=time.perf_counter)
        control, both = ratio["step + control"], ratio["step + capture all + control"]
        print(f"{name:14s} {layers:6d} {plain:9.1f} {control * plain:10.1f} {control:6.3f} {both * plain:14.1f} "
              f"{both:6.3f}")
    print(f"median wall time of {args.repeats} policy steps; ratios: median of {args.repeats} paired rounds; "
          "control: the minimal controller at the second layer with "
          "its readings logged, its box beyond every reading so it acts at every forward; all: every layer captured")


if __name__ == "__main__":
    main()
