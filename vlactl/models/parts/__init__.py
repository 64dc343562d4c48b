"""Building blocks shared by the embedded models: vision tokens, text tokens, normalisation, prefix, checkpoints."""
