"""Compacting a trained avatar for inference: pruning, F_dw baked, F_a folded, refit, each checked by rendering.
Imports lightning, model, data, evaluation and below; only the entry points (prune, export) and tools import it."""
