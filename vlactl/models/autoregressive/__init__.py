"""OpenVLA-style autoregressive VLA: a Llama decoder that writes each action dimension as one of 256 bin tokens."""
