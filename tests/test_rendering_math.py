"""The torch volume rendering matches the numpy reference, and stays finite for any finite input."""

import numpy as np
import pytest
import torch

from noisenerf.runtime import compositing as np_render
from noisenerf.runtime.encoding import positional_encoding as np_encoding
from noisenerf.runtime.pdf import sample_pdf
from noisenerf.runtime.sampling import LAST_DELTA
from noisenerf.train.scene import render as torch_render
from noisenerf.train.scene.field import positional_encoding as torch_encoding


def random_rays(seed, n_rays=64, n_samples=32, scale=10.0):
    rng = np.random.default_rng(seed)
    sigmas = (rng.random((n_rays, n_samples)) * scale).astype(np.float32)
    sigmas[rng.random(sigmas.shape) < 0.3] = 0.0
    deltas = (rng.random((n_rays, n_samples)) * 0.1).astype(np.float32)
    deltas[:, -1] = LAST_DELTA
    rgbs = rng.random((n_rays, n_samples, 3)).astype(np.float32)
    return sigmas, deltas, rgbs


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3, 3e38])
def test_torch_matches_numpy_reference(scale):
    sigmas, deltas, rgbs = random_rays(0, scale=scale)
    background = np.array([1.0, 0.5, 0.0], dtype=np.float32)
    ref = np_render.composite(np_render.render_weights(sigmas, deltas), rgbs, background)
    weights = torch_render.render_weights(torch.from_numpy(sigmas), torch.from_numpy(deltas))
    out = torch_render.composite(weights, torch.from_numpy(rgbs), torch.from_numpy(background)).numpy()
    assert np.isfinite(ref).all() and np.isfinite(out).all()
    assert np.abs(out - ref).max() <= 1e-6


def test_transmittance_is_exclusive_and_exponential():
    depths = np.array([[0.5, 1.0, 2.0]], dtype=np.float32)
    expected = np.exp(-np.array([[0.0, 0.5, 1.5]], dtype=np.float32))
    np.testing.assert_allclose(np_render.transmittance(depths), expected, rtol=1e-7)
    np.testing.assert_allclose(torch_render.transmittance(torch.from_numpy(depths)).numpy(), expected, rtol=1e-7)


def test_degenerate_densities_stay_finite():
    # all-zero densities render the background; overflowing σ·Δ saturates instead of producing inf/NaN
    sigmas = np.array([[0.0, 0.0, 0.0], [np.finfo(np.float32).max, 1.0, 0.0]], dtype=np.float32)
    deltas = np.array([[0.1, 0.1, LAST_DELTA], [LAST_DELTA, 0.1, LAST_DELTA]], dtype=np.float32)
    rgbs = np.full((2, 3, 3), 0.25, dtype=np.float32)
    bg = np.ones(3, np.float32)
    colors = np_render.composite(np_render.render_weights(sigmas, deltas), rgbs, bg)
    np.testing.assert_array_equal(colors[0], bg)
    np.testing.assert_allclose(colors[1], 0.25, atol=1e-7)
    weights = torch_render.render_weights(torch.from_numpy(sigmas), torch.from_numpy(deltas))
    assert torch.isfinite(weights).all()
    assert torch.allclose(weights.sum(1), torch.tensor([0.0, 1.0]))


def test_encoding_matches_between_numpy_and_torch_and_has_nerf_pytorch_layout():
    x = np.random.default_rng(1).normal(size=(10, 3)).astype(np.float32)
    ref = np_encoding(x, 4)
    assert ref.shape == (10, 27)
    np.testing.assert_array_equal(ref[:, :3], x)
    np.testing.assert_allclose(ref[:, 3:6], np.sin(x), rtol=1e-6)
    np.testing.assert_allclose(ref[:, 6:9], np.cos(x), rtol=1e-6)
    np.testing.assert_allclose(ref[:, 9:12], np.sin(2 * x), rtol=1e-6)
    np.testing.assert_allclose(torch_encoding(torch.from_numpy(x), 4).numpy(), ref, atol=1e-6)


def test_occupancy_box_is_closed_so_the_ndc_far_plane_sample_is_kept():
    from noisenerf.runtime.occupancy import OccupancyGrid

    occupied = np.zeros((4, 4, 4), dtype=bool)
    occupied[3, 3, 3] = occupied[0, 0, 0] = True
    grid = OccupancyGrid((-1, -1, -1, 1, 1, 1), occupied)
    points = np.array([[1, 1, 1], [0.9, 0.9, 1.0], [-1, -1, -1], [0.9, 0.9, 1.0001], [0, 0, 0]], np.float32)
    assert grid.lookup(points).tolist() == [True, True, True, False, False]


def test_numpy_sample_pdf_matches_the_torch_twin():
    """Peaked, flat and all-zero weights (the 1e-5 floor and the denominator guard), over rays' own bins.

    Equal up to float32 rounding of u and of the pdf's normaliser (numpy and torch sum in another order,
    as torch does between CPU and CUDA), which (u − cdf)/pdf amplifies: ~1e-5 of a bin of width 0.13.
    The last sample (u = 1) is compared loosely: it lands wherever cdf[-1] rounds, either side of 1,
    but always in the last bin."""
    rng = np.random.default_rng(5)
    weights = rng.random((96, 31)).astype(np.float32) ** 2
    weights[32:64] = 0.0
    weights[64:, 10] = 50.0
    bins = np.sort(rng.random((96, 32)).astype(np.float32) * 4 + 2, axis=1)
    ours = sample_pdf(bins, weights, 40)
    theirs = torch_render.sample_pdf(torch.from_numpy(bins), torch.from_numpy(weights), 40).numpy()
    assert ours.dtype == np.float32 and ours.shape == (96, 40)
    assert np.all(np.diff(ours, axis=1) >= 0)
    np.testing.assert_allclose(ours[:, :-1], theirs[:, :-1], rtol=0, atol=2e-4)
    assert np.all((ours[:, -1] >= bins[:, -2]) & (ours[:, -1] <= bins[:, -1]))
