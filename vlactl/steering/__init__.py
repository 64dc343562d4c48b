"""The paper's math (linear observers, the minimum-norm controller) as plain tensor code, and the activation store."""
