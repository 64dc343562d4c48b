"""`vlactl train-policy`: training the embedded models on demonstrations."""
