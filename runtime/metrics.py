"""Image quality metrics in numpy: PSNR, SSIM, and the exactness of 8-bit recovery.

SSIM uses data_range = 1 and an 11×11 Gaussian window (σ = 1.5) over the valid region, averaged over
channels, as tf.image.ssim does. `ssim_authors` is the variant the paper's public code reports
(scikit-image's defaults there: a 7×7 uniform window, sample covariance, and a lenient data_range of 2).
"""

from __future__ import annotations

import numpy as np

from noisenerf.runtime.images import to_uint8

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
AUTHORS_WINDOW = 7
AUTHORS_DATA_RANGE = 2.0


def psnr(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (inf for identical images). a, b: (..., 3) in [0, data_range]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(data_range ** 2 / mse))


def gaussian_kernel() -> np.ndarray:
    """The 11-tap Gaussian (σ = 1.5), normalised. -> (11,)."""
    x = np.arange(SSIM_WINDOW) - SSIM_WINDOW // 2
    kernel = np.exp(-(x ** 2) / (2 * SSIM_SIGMA ** 2))
    return kernel / kernel.sum()


def _filter_valid(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Separable filter without padding. image: (H, W, C), kernel: (k,) -> (H − k + 1, W − k + 1, C)."""
    k = kernel.size
    rows = sum(kernel[i] * image[i:image.shape[0] - k + 1 + i] for i in range(k))
    return sum(kernel[i] * rows[:, i:rows.shape[1] - k + 1 + i] for i in range(k))


def _ssim(a: np.ndarray, b: np.ndarray, data_range: float, kernel: np.ndarray, covariance_scale: float) -> float:
    """Mean SSIM over the valid windows and channels for a given window (statistics scaled by
    covariance_scale: 1, or N/(N − 1) for sample covariance). a, b: (H, W, C)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3 or min(a.shape[:2]) < kernel.size:
        raise ValueError(f"ssim needs two equal (H, W, C) images of at least {kernel.size}×{kernel.size}, "
                         f"got {a.shape}, {b.shape}")
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = _filter_valid(a, kernel), _filter_valid(b, kernel)
    var_a = covariance_scale * (_filter_valid(a * a, kernel) - mu_a ** 2)
    var_b = covariance_scale * (_filter_valid(b * b, kernel) - mu_b ** 2)
    cov = covariance_scale * (_filter_valid(a * b, kernel) - mu_a * mu_b)
    score = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(score.mean())


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity, 11×11 Gaussian window, mean over the valid windows and channels.
    a, b: (H, W, C), H, W ≥ 11."""
    return _ssim(a, b, data_range, gaussian_kernel(), 1.0)


def ssim_authors(a: np.ndarray, b: np.ndarray) -> float:
    """The paper's public code's SSIM: skimage.metrics.structural_similarity with data_range 2 (7×7
    uniform window, sample covariance, border windows dropped). a, b: (H, W, C) in [0, 1], H, W ≥ 7."""
    n = AUTHORS_WINDOW ** 2
    return _ssim(a, b, AUTHORS_DATA_RANGE, np.full(AUTHORS_WINDOW, 1.0 / AUTHORS_WINDOW), n / (n - 1))


def exact_fraction(pixels: np.ndarray, target: np.ndarray) -> float:
    """Share of 8-bit values recovered exactly. pixels, target: (..., 3) uint8."""
    return float(np.mean(np.asarray(pixels) == np.asarray(target)))


def rounding_margins(colors: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """How far each rendered value lies inside the 8-bit bin of its target, in levels: 255·c against the bin
    [t − ½, t + ½) that to_uint8 rounds into t (0 and 255 open outward: no boundary there), positive inside, negative
    outside. A value that rounds right survives any error smaller than its margin. colors: (..., 3) float in
    [0, 1], pixels: (..., 3) uint8 -> (..., 3) float64 (inf for a value whose bin has no boundary on either side)."""
    levels, target = np.asarray(colors, np.float64) * 255, pixels.astype(np.float64)
    below = np.where(pixels > 0, levels - (target - 0.5), np.inf)
    above = np.where(pixels < 255, (target + 0.5) - levels, np.inf)
    return np.minimum(below, above)


def tile_quality(colors: np.ndarray, pixels: np.ndarray, shape: tuple[int, int]) -> dict:
    """A rendered tile against its 8-bit target: exact fraction (of values), pixels with any value off, max
    error, the smallest rounding margin in levels (rounding_margins), PSNR, SSIM (None under 11 px). colors: (n, 3)
    float in [0, 1], pixels: (n, 3) uint8, shape: the tile's (height, width)."""
    image, target = colors.reshape(*shape, 3), pixels.reshape(*shape, 3)
    got = to_uint8(image)
    return {
        "exact_fraction": exact_fraction(got, target),
        "inexact_pixels": int((got != target).any(-1).sum()),
        "margin_levels": float(rounding_margins(image, target).min()),
        "max_error": int(np.abs(got.astype(np.int16) - target).max()),
        "psnr": psnr(got / 255.0, target / 255.0),
        "ssim": ssim(got / 255.0, target / 255.0) if min(shape) >= 11 else None,
    }
