"""A small activation folder with the SPEC features planted in known layers, written the way `vlactl collect` does."""

from pathlib import Path

from vlactl.steering.activations import FEATURES, ActivationWriter
from vlactl.steering.synthetic import Planted, planted_activations, spec_labels


def write_store(folder: Path, n_layers=4, n_episodes=16, frames=20, d=16, dtype="float16", shard_size=100,
                model="synthetic", seed=0) -> Planted:
    data = planted_activations(n_layers, n_episodes, frames, d, len(FEATURES), planted_every=2, seed=seed)
    labels = spec_labels(data.latent, data.episodes)
    layers = [f"backbone.{i}" for i in range(n_layers)]
    with ActivationWriter(folder, model=model, layers=layers, widths={name: d for name in layers}, pooling="prefix",
                          dtype=dtype, shard_size=shard_size) as writer:
        for e in range(n_episodes):
            rows = data.episodes == e
            writer.append({name: data.x[i, rows] for i, name in enumerate(layers)}, labels[rows])
    return data
