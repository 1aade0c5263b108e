"""The hash-grid field kind against its specification (tiny-cuda-nn's / Instant-NGP's conventions, the
figures in ../shared/research/nerfacto-import.md §2), written here independently of the implementation:
per-level layouts and parameter counts, the uint32 hash, dense indexing with its wraparound, trilinear
weights, the spherical harmonics, the hand-written Jacobian; then a hash-grid scene through the command
lines (tiles, a sealed payload, ordinary renders)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from helpers import fitted_tiny_scene, make_tiny_scene, run_main, run_reveal, tcnn_sh
from noisenerf.cli.main import main
from noisenerf.runtime.fields.hashgrid import grid_levels, sh_matrix
from noisenerf.runtime.images import read_native, to_uint8, write_image
from noisenerf.runtime.render import render_view
from noisenerf.train.scene.procedural import procedural_secret
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.hashgrid import HashGridConfig, HashGridField
from noisenerf.train.scene.random_scene import SMALL_HASHGRID


@pytest.mark.parametrize("levels, log2_table, max_resolution, resolutions, dense, parameters", [
    # nerfacto's field: levels 0-4 dense (4096, 12168, 29792, 79512, 205384 rows), 5-15 hashed at 2^19
    (16, 19, 2048, (16, 23, 31, 43, 59, 81), 5, 12_196_240),
    (5, 17, 128, (16, 27, 46, 77, 128), 3, 766_528),  # nerfacto's first proposal network
    (5, 17, 256, (16, 32, 64, 128, 256), 2, 860_160),  # its second: b = 2, scales exactly 15, 31, 63, …
])
def test_level_layout_and_parameter_counts_are_tiny_cuda_nns(levels, log2_table, max_resolution, resolutions, dense,
                                                              parameters):
    layout = grid_levels(levels, log2_table, 16, HashGridConfig.per_level_scale_for(16, max_resolution, levels))
    assert tuple(layout.resolution[:len(resolutions)]) == resolutions
    assert layout.dense.tolist() == [1] * dense + [0] * (levels - dense)
    assert layout.total_rows * 2 == parameters
    assert layout.offset.tolist() == np.concatenate([[0], np.cumsum(layout.rows)[:-1]]).tolist()


def reference_encoding(table: np.ndarray, points: np.ndarray, config: HashGridConfig) -> np.ndarray:
    """The hash encoding corner by corner as tiny-cuda-nn describes it: uint32 hash with wrapping products,
    dense index x + y·res + z·res² modulo the level's rows, weights Π_d (bit ? frac : 1 − frac)."""
    layout = grid_levels(config.levels, config.log2_table, config.base_resolution, config.per_level_scale)
    lo, hi = np.float32(config.aabb[:3]), np.float32(config.aabb[3:])
    unit = np.clip((points - lo) / (hi - lo), 0, 1).astype(np.float32)
    out = np.zeros((len(points), config.levels, config.features), np.float32)
    primes = np.array([1, 2654435761, 805459861], np.uint32)
    for level in range(config.levels):
        position = unit * layout.scale[level] + np.float32(0.5)
        cell = np.floor(position)
        fraction, cell = position - cell, cell.astype(np.int64)
        for corner in range(8):
            bits = np.array([(corner >> d) & 1 for d in range(3)])
            vertex = cell + bits
            if layout.dense[level]:
                res = int(layout.resolution[level])
                index = (vertex[:, 0] + vertex[:, 1] * res + vertex[:, 2] * res * res) % layout.rows[level]
            else:
                with np.errstate(over="ignore"):
                    terms = vertex.astype(np.uint32) * primes
                index = (terms[:, 0] ^ terms[:, 1] ^ terms[:, 2]).astype(np.int64) % layout.rows[level]
            weight = np.prod(np.where(bits, fraction, 1 - fraction), axis=1)
            out[:, level] += weight[:, None] * table[layout.offset[level] + index]
    return out.reshape(len(points), -1)


def test_the_encoding_is_the_reference_corner_by_corner():
    config = HashGridConfig(levels=8, features=2, log2_table=12, base_resolution=4, per_level_scale=1.7)
    torch.manual_seed(0)
    field = HashGridField(config)
    field.table.data.uniform_(-1, 1)
    rng = np.random.default_rng(0)
    # inside the box, on its faces, outside it (clamped), and on vertices where frac is exactly 0
    points = np.concatenate([rng.uniform(-1.5, 1.5, (500, 3)), rng.uniform(-3, 3, (200, 3)),
                             np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5], [0.0, 0.0, 0.0]])]).astype(np.float32)
    with torch.no_grad():
        ours = field.grid_features(torch.from_numpy(points)).numpy()
    assert grid_levels(8, 12, 4, 1.7).dense.tolist().count(1) in range(1, 8)  # both kinds of level are covered
    np.testing.assert_allclose(ours, reference_encoding(field.table.detach().numpy(), points, config), atol=2e-6)


def test_dense_levels_wrap_around_their_rows():
    """The +0.5 offset puts the upper corner of the last cell one vertex past the grid (res³ entries, the
    table rounded up to 8): tiny-cuda-nn's index modulo the level's rows wraps it, as here."""
    layout = grid_levels(1, 12, 5, 2.0)
    res, rows = int(layout.resolution[0]), int(layout.rows[0])
    assert (res, rows) == (5, 128)  # 125 vertices rounded up to a multiple of 8
    config = HashGridConfig(levels=1, features=1, log2_table=12, base_resolution=5, per_level_scale=2.0,
                            aabb=(0, 0, 0, 1, 1, 1))
    field = HashGridField(config)
    field.table.data = torch.arange(rows, dtype=torch.float32)[:, None]
    top = torch.tensor([[1.0, 1.0, 1.0]])  # scale 4: position 4.5, cell 4, frac 0.5; upper vertex 5 is past the grid
    expected = np.mean([((4 + b0) + (4 + b1) * res + (4 + b2) * res * res) % rows
                        for b0 in (0, 1) for b1 in (0, 1) for b2 in (0, 1)])
    with torch.no_grad():
        assert float(field.grid_features(top)) == pytest.approx(expected)


def test_a_hashed_corner_is_instant_ngps_uint32_hash():
    """Python integers, no fixed width: (x·1 ⊕ y·2654435761 ⊕ z·805459861) mod 2^32, then mod the rows."""
    config = HashGridConfig(levels=1, features=1, log2_table=4, base_resolution=64, per_level_scale=2.0,
                            aabb=(0, 0, 0, 1, 1, 1))
    field = HashGridField(config)
    field.table.data = torch.arange(16, dtype=torch.float32)[:, None]
    point = np.array([[0.16, 0.32, 0.48]], np.float32)
    position = point[0] * np.float32(63.0) + np.float32(0.5)  # scale 64 − 1; 64³ vertices do not fit 16 rows
    cell, fraction = np.floor(position).astype(int), position - np.floor(position)
    expected = 0.0
    for corner in range(8):
        x, y, z = (int(cell[d]) + ((corner >> d) & 1) for d in range(3))
        hashed = ((x * 1) ^ (y * 2654435761) ^ (z * 805459861)) % 2 ** 32 % 16
        expected += hashed * np.prod([fraction[d] if (corner >> d) & 1 else 1 - fraction[d] for d in range(3)])
    with torch.no_grad():
        assert float(field.grid_features(torch.from_numpy(point))) == pytest.approx(expected, abs=1e-4)


def test_spherical_harmonics_are_the_real_basis_of_degree_4():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    expected = tcnn_sh(d)
    field = HashGridField(SMALL_HASHGRID)
    with torch.no_grad():
        ours = field.spherical_harmonics(torch.from_numpy(d.astype(np.float32))).numpy()
    np.testing.assert_allclose(ours, expected, atol=2e-6)
    # orthonormal on the sphere: the Gram matrix of many samples approaches I / (4π)
    many = rng.normal(size=(200_000, 3))
    many /= np.linalg.norm(many, axis=1, keepdims=True)
    matrix, constant = sh_matrix()
    x, y, z = many.T
    monomials = np.stack([x, y, z, x * x, x * y, x * z, y * y, y * z, z * z, x ** 3, x * x * y, x * x * z, x * y * y,
                          x * y * z, x * z * z, y ** 3, y * y * z, y * z * z, z ** 3], 1)
    values = monomials @ matrix.T.astype(np.float64) + constant
    gram = values.T @ values / len(many) * 4 * np.pi
    np.testing.assert_allclose(gram, np.eye(16), atol=0.02)


def test_the_hand_written_jacobian_is_autograds():
    field = make_tiny_scene(seed=5, kind="hashgrid").coarse
    torch.manual_seed(0)
    encoded = field.encode(torch.rand(16, 3) * 3 - 1.5, torch.nn.functional.normalize(torch.randn(16, 3), dim=-1))
    encoded = encoded + torch.randn_like(encoded)
    outputs, jacobian = field.outputs_and_jacobian(encoded)

    def raw(row):
        rgb, density = field.raw_outputs(row[None])
        return torch.cat([rgb[0], density])

    expected = torch.stack([torch.autograd.functional.jacobian(raw, row) for row in encoded])
    torch.testing.assert_close(jacobian, expected, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(outputs, torch.stack([raw(row) for row in encoded]))
    assert not jacobian[:, 3, field.config.position_dims:].any()  # density never reads the direction segment


def test_the_table_gradient_is_the_encodings_transpose():
    """GridGather's index_add backward: the encoding is linear in the table, f = A·table, so the gradient G of
    Σ f² is 2·Aᵀf and ⟨G, V⟩ = 2·⟨f, A·V⟩ for any V, with A·V the reference encoding of the table V."""
    field = HashGridField(SMALL_HASHGRID)
    field.table.data.uniform_(-1, 1)
    points = torch.rand(300, 3) * 3 - 1.5
    features = field.grid_features(points)
    features.pow(2).sum().backward()
    rng = np.random.default_rng(2)
    for _ in range(3):
        direction = rng.normal(size=field.table.shape).astype(np.float32)
        along = reference_encoding(direction, points.numpy(), SMALL_HASHGRID)
        expected = 2 * float((features.detach().numpy().astype(np.float64) * along).sum())
        assert float((field.table.grad.numpy().astype(np.float64) * direction).sum()) == pytest.approx(expected,
                                                                                                       rel=1e-4)


@pytest.fixture(scope="module")
def hashgrid_model(tmp_path_factory):
    """A random hash-grid scene (tests/helpers.make_tiny_scene) saved and exported: (folder, scene)."""
    from noisenerf.export.onnx_export import export_scene

    folder = tmp_path_factory.mktemp("hashgrid")
    scene = make_tiny_scene(seed=6, kind="hashgrid")
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return folder, scene


def test_tiles_a_sealed_payload_and_ordinary_renders_work_on_a_hash_grid(hashgrid_model, tmp_path, capfd):
    """What works for the mlp kind works for the hash grid, through the command lines: a secret cut into
    tiles (at several cameras), a sealed file payload, an ordinary render equal to torch's."""
    folder, scene = hashgrid_model
    secret = procedural_secret(24, 16, seed=3)
    write_image(tmp_path / "secret.png", secret)
    assert run_main(main, ["hide", folder / "scene", tmp_path / "secret.png", "-o", tmp_path / "tiled.bundle",
                           "--tile-size", "16", "--quiet", "--json"], capfd).code == 0
    revealed = run_reveal(folder / "model.onnx", tmp_path / "tiled.bundle", "-o", tmp_path / "out.png", "--json")
    assert revealed.returncode == 0, revealed.stderr
    assert json.loads(revealed.stdout)["exact"] is True
    assert np.array_equal(read_native(tmp_path / "out.png")[..., :3], secret)

    payload = tmp_path / "note.txt"
    payload.write_bytes(b"hidden in a hash grid\n" * 5)
    (tmp_path / "pass.txt").write_text("correct horse battery staple")
    assert run_main(main, ["hide", folder / "scene", "--file", payload, "-o", tmp_path / "p.bundle",
                           "--passphrase-file", tmp_path / "pass.txt", "--quiet"], capfd).code == 0
    opened = run_reveal(folder / "model.onnx", tmp_path / "p.bundle", "-o", tmp_path / "note.out",
                        "--passphrase-file", tmp_path / "pass.txt")
    assert opened.returncode == 0, opened.stderr
    assert (tmp_path / "note.out").read_bytes() == payload.read_bytes()

    rendered = run_reveal(folder / "model.onnx", "--view", "1", "-o", tmp_path / "view.png")
    assert rendered.returncode == 0, rendered.stderr
    image, _ = render_view(scene.config.cameras[1], scene.config.render, numpy_field(scene.render_field), scene.sampler())
    ours = read_native(tmp_path / "view.png")[..., :3].astype(int)
    assert np.abs(ours - to_uint8(image).astype(int)).max() <= 1  # torch and onnxruntime agree to float32 rounding


def test_the_samples_the_paper_method_leaves_out_move_a_colour_by_under_half_a_step(tmp_path):
    """Exp density has no dead samples; `negligible` leaves out each ray's least opaque ones while their σΔ
    sum stays under half an 8-bit step: rendered with their checked density and colour 0 (as the paper's
    skipping passes do), every ray's colour is within half a step of the full render."""
    from noisenerf.runtime.bundle import Tile
    from noisenerf.runtime.sampling import SamplingConfig
    from noisenerf.train.hide.secret_view import SecretView

    scene = fitted_tiny_scene(tmp_path, "hashgrid")  # a fitted scene has empty space: a random one has none
    camera = scene.config.cameras[2]
    tile = Tile((0, 0, camera.width, camera.height), camera, SamplingConfig(2.0, 6.0, 48), None)
    view = SecretView(scene.coarse, tile, scene.config.render, torch.device("cpu"))
    index = torch.arange(view.n_rays)
    noise = 0.1 * torch.randn(view.n_rays, view.n_samples, view.noise_dims, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        raw_rgb, raw_density = view.raw(index, noise)
        left_out = view.field.negligible(raw_density, view.deltas)
        full = view.shade(index, raw_rgb, raw_density)
        skipped = view.shade(index, torch.where(left_out[..., None], 0.0, raw_rgb), raw_density)
    assert 0.0 < float(left_out.float().mean()) < 1.0  # the rule leaves samples out, not all (a young fit: ~7 %)
    assert float((torch.sigmoid(raw_rgb) * left_out[..., None]).amax()) > 0  # and those had colour to lose
    assert float((full - skipped).abs().max()) < 0.5 / 255
