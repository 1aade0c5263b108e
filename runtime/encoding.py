"""Positional encoding γ (paper eq. 4), in nerf-pytorch's layout, as the numpy reference."""

import numpy as np


def encoding_dims(n_freqs: int) -> int:
    """Width of γ for a 3-vector with the raw input included: 3 + 3·2·L."""
    return 3 + 6 * n_freqs


def positional_encoding(x: np.ndarray, n_freqs: int) -> np.ndarray:
    """γ(x) = [x, sin(2⁰x), cos(2⁰x), …, sin(2^{L-1}x), cos(2^{L-1}x)].

    x: (..., 3) float32 -> (..., 3 + 6·n_freqs) float32, the order nerf-pytorch's Embedder uses.
    """
    x = np.asarray(x, dtype=np.float32)
    parts = [x]
    for freq in (2.0 ** np.arange(n_freqs)).astype(np.float32):
        parts += [np.sin(x * freq), np.cos(x * freq)]
    return np.concatenate(parts, axis=-1)
