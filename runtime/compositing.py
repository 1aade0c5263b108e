"""Volume rendering (paper eq. 2) in numpy: the reference the torch and onnxruntime paths must match.

Transmittance is exp(−exclusive cumsum(σ·Δ)), never a cumprod: it is stable, exports to ONNX CumSum
and agrees between numpy and torch. σ·Δ is capped at MAX_OPTICAL_DEPTH so that huge densities and the
1e10 last interval never overflow to inf (exp(−1e4) is already exactly 0 in float32).
"""

import numpy as np

MAX_OPTICAL_DEPTH = 1e4


def optical_depths(sigmas: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """σ·Δ per sample, capped. sigmas, deltas: (n_rays, n_samples) -> (n_rays, n_samples)."""
    with np.errstate(over="ignore"):
        depth = np.asarray(sigmas, np.float32) * np.asarray(deltas, np.float32)
    return np.minimum(depth, np.float32(MAX_OPTICAL_DEPTH))


def transmittance(depths: np.ndarray) -> np.ndarray:
    """T_i = exp(−Σ_{j<i} σ_jΔ_j). depths: (n_rays, n_samples) -> (n_rays, n_samples)."""
    exclusive = np.concatenate(
        [np.zeros_like(depths[:, :1]), np.cumsum(depths, axis=1, dtype=np.float32)[:, :-1]], axis=1
    )
    return np.exp(-exclusive)


def render_weights(sigmas: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """w_i = T_i·(1 − exp(−σ_iΔ_i)). sigmas, deltas: (n_rays, n_samples) -> (n_rays, n_samples)."""
    depths = optical_depths(sigmas, deltas)
    return transmittance(depths) * -np.expm1(-depths)


def composite(weights: np.ndarray, rgbs: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Ĉ = Σ w_i c_i + (1 − Σ w_i)·background.

    weights: (n_rays, n_samples), rgbs: (n_rays, n_samples, 3), background: (3,) -> (n_rays, 3).
    """
    opacity = weights.sum(axis=1, dtype=np.float32)
    color = np.einsum("rs,rsc->rc", weights, rgbs, dtype=np.float32)
    return (color + (1.0 - opacity)[:, None] * np.asarray(background, np.float32)).astype(np.float32)
