"""The paper's figures, one module per kind, each drawn from a stage's output files (never from a model)."""
