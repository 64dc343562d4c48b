"""A word-level tokenizer trained here on the dataset's instructions (`tokenizers`), saved with the checkpoint."""

from __future__ import annotations

from pathlib import Path

import torch
from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, trainers

PAD, UNK = "[PAD]", "[UNK]"


def train_tokenizer(texts: list[str]) -> Tokenizer:
    """Words seen in training get ids; anything else (e.g. a constraint said in a prompt) maps to [UNK]."""
    tok = Tokenizer(models.WordLevel(unk_token=UNK))
    tok.normalizer = normalizers.Sequence([normalizers.NFKC(), normalizers.Lowercase()])
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.train_from_iterator(texts, trainers.WordLevelTrainer(special_tokens=[PAD, UNK]))
    return tok


def load_tokenizer(path: Path) -> Tokenizer:
    return Tokenizer.from_file(str(path))


def encode(tok: Tokenizer, texts: list[str], length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Ids [B, length] right-padded (or truncated) to a fixed length, and the mask of real tokens.

    A fixed length keeps every prompt the same shape, so the pads are ordinary attended tokens and no attention
    mask is needed; the mask only keeps them out of the `text` read-out.
    """
    pad = tok.token_to_id(PAD)
    ids = torch.full((len(texts), length), pad, dtype=torch.long)
    for row, enc in enumerate(tok.encode_batch(list(texts))):
        words = enc.ids[:length]
        ids[row, : len(words)] = torch.tensor(words, dtype=torch.long)
    return ids, ids != pad
