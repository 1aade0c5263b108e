"""Image quality metrics in numpy: PSNR, SSIM, and the exactness of 8-bit recovery.

SSIM uses data_range = 1 and an 11×11 Gaussian window (σ = 1.5) over the valid region, averaged over
channels, as tf.image.ssim does; the paper's public code used a lenient data_range of 2.
"""

from __future__ import annotations

import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def psnr(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (inf for identical images). a, b: (..., 3) in [0, data_range]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(data_range ** 2 / mse))


def _gaussian_filter_valid(image: np.ndarray) -> np.ndarray:
    """Separable 11×11 Gaussian filter without padding. image: (H, W, C) -> (H − 10, W − 10, C)."""
    x = np.arange(SSIM_WINDOW) - SSIM_WINDOW // 2
    kernel = np.exp(-(x ** 2) / (2 * SSIM_SIGMA ** 2))
    kernel /= kernel.sum()
    rows = sum(kernel[i] * image[i:image.shape[0] - SSIM_WINDOW + 1 + i] for i in range(SSIM_WINDOW))
    return sum(kernel[i] * rows[:, i:rows.shape[1] - SSIM_WINDOW + 1 + i] for i in range(SSIM_WINDOW))


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity, mean over the valid windows and channels. a, b: (H, W, C), H, W ≥ 11."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3 or min(a.shape[:2]) < SSIM_WINDOW:
        raise ValueError(f"ssim needs two equal (H, W, C) images of at least 11×11, got {a.shape}, {b.shape}")
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = _gaussian_filter_valid(a), _gaussian_filter_valid(b)
    var_a = _gaussian_filter_valid(a * a) - mu_a ** 2
    var_b = _gaussian_filter_valid(b * b) - mu_b ** 2
    cov = _gaussian_filter_valid(a * b) - mu_a * mu_b
    score = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(score.mean())


def exact_fraction(pixels: np.ndarray, target: np.ndarray) -> float:
    """Share of 8-bit values recovered exactly. pixels, target: (..., 3) uint8."""
    return float(np.mean(np.asarray(pixels) == np.asarray(target)))
