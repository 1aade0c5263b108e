"""`noisenerf hide`: train the noise that makes a frozen scene render a secret (Noise-NeRF).

Work is split into tiles (one viewpoint each) and, in exact mode, into fixed chunks of pixels solved
independently; each finished chunk is saved beside the output (OUT.partial/), so an interrupted hide
run again with the same arguments resumes where it stopped and writes a byte-identical bundle.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from tqdm import tqdm

import noisenerf
from noisenerf.runtime.bundle import LAYOUT_DTYPES, LAYOUTS, Bundle, Frame, Tile, secret_digest
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import atomic_output, check_output_path, existing_kind
from noisenerf.runtime.limits import MAX_RAY_LAYOUT_SAMPLES, checked_image_size
from noisenerf.runtime.metrics import exact_fraction, psnr, ssim
from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.sampling import NETWORKS, SamplingConfig, render_network
from noisenerf.train.scene.scene import Scene
from noisenerf.train.hide.secret_view import SecretView
from noisenerf.train.hide.paper import PaperSettings, pass_slices, recorded_points, solve_blocks, survey
from noisenerf.train.hide.compact import INTEGER_DTYPES, CompactSettings, tile_space
from noisenerf.train.hide.exact import ExactSettings, NoiseSpace, solve_exact
from noisenerf.train.hide.tiling import tile_camera, tile_rects

TORCH_DTYPES = {"float16": torch.float16, "float32": torch.float32, **INTEGER_DTYPES}
DEFAULT_LAYOUTS = {"exact": "compact", "paper": "sample"}
EXACT_CPU_THREADS = 1  # see solver_threads
ESCAPE_DTYPE = torch.float16  # a compact tile's escaped pixels store full noise as the ray layout does


PAPER_SAMPLES = 64  # nerf-pytorch's N_samples, the coarse sampling the paper's code renders with


@dataclass(frozen=True)
class HideConfig:
    """Everything that decides a bundle's bytes (saved in the bundle, and keyed for resume).

    The exact method's secret view has one sample per ray (see solvers.py: it makes every pixel a
    piecewise-linear problem); the paper's method samples PAPER_SAMPLES points per ray by default.
    Layouts (runtime/bundle.py): exact stores `compact` by default (int16 coefficients of a per-tile
    basis, see compact.py) or `ray` (float noise per pixel); paper stores `sample` (or `ray`). The dtype
    defaults to the layout's first (int16, float16, float32).
    `network` is the one the secret view renders through, recorded per tile: by default the coarse
    network for the paper's method (as its authors render), the scene's render network for exact.
    """

    method: str = "exact"  # exact | paper
    layout: str | None = None  # compact | ray | sample; None: the method's default
    dtype: str | None = None  # None: the layout's default
    n_samples: int | None = None  # samples per ray of the secret view; None: the method's default
    tile_size: int = 512
    view: int = 0
    seed: int = 0
    chunk_pixels: int = 16384  # exact method: pixels per solved (and resumable) chunk; CLI: chunk_pixels_for
    network: str | None = None  # coarse | fine; None: the scene's render network
    exact: ExactSettings = ExactSettings()
    paper: PaperSettings = PaperSettings()
    compact: CompactSettings = CompactSettings()

    def __post_init__(self):
        if self.method not in DEFAULT_LAYOUTS:
            raise UserError(f"unknown method {self.method!r} (exact or paper)")
        if self.layout is None:
            object.__setattr__(self, "layout", DEFAULT_LAYOUTS[self.method])
        if self.layout not in LAYOUTS:
            raise UserError(f"unknown noise layout {self.layout!r} (one of {', '.join(LAYOUTS)})")
        if self.layout == "compact" and self.method != "exact":
            raise UserError("the compact layout is the exact method's (the paper's method stores sample or ray)")
        if self.dtype is None:
            object.__setattr__(self, "dtype", LAYOUT_DTYPES[self.layout][0])
        if self.dtype not in LAYOUT_DTYPES[self.layout]:
            raise UserError(f"the {self.layout} layout stores {' or '.join(LAYOUT_DTYPES[self.layout])}, "
                            f"not {self.dtype!r}")
        if self.n_samples is None:
            object.__setattr__(self, "n_samples", 1 if self.method == "exact" else PAPER_SAMPLES)
        if self.network is None and self.method == "paper":
            object.__setattr__(self, "network", "coarse")
        if self.network not in (None, *NETWORKS):
            raise UserError(f"unknown network {self.network!r} (coarse or fine)")
        if self.n_samples < 1:
            raise UserError("the secret view needs at least one sample per ray")
        if self.method == "exact" and self.n_samples != 1:
            raise UserError("--method exact renders its secret view with one sample per ray (--samples 1)")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class HidePlan:
    """The tiles to solve: rectangles, cameras and the secret's pixels for each."""

    tiles: tuple[Tile, ...]  # noise still empty
    secret: np.ndarray  # (H, W, 3) uint8


def plan(scene: Scene, secret: np.ndarray, config: HideConfig) -> HidePlan:
    height, width = secret.shape[:2]
    if height < 1 or width < 1:
        raise UserError("the secret image is empty")
    n_cameras = len(scene.config.cameras)
    if not 0 <= config.view < n_cameras:
        raise UserError(f"--view {config.view} is out of range: the scene has {n_cameras} cameras (0..{n_cameras - 1})")
    network = config.network or render_network(scene.fields())
    if network not in scene.fields():
        raise UserError(f"the scene has no {network} network")
    sampling = SamplingConfig(scene.config.render.sampling.near, scene.config.render.sampling.far, config.n_samples)
    tiles = tuple(Tile(rect=rect, camera=tile_camera(scene.config.cameras, config.view, k, rect), sampling=sampling,
                       noise=np.zeros(0, np.float32), view=(config.view + k) % n_cameras, network=network)
                  for k, rect in enumerate(tile_rects(width, height, config.tile_size)))
    return HidePlan(tiles, secret)


def run_key(scene: Scene, secret: np.ndarray, config: HideConfig) -> str:
    """What a resumable partial result belongs to: scene, secret and every setting."""
    payload = json.dumps({"scene": scene.fingerprint(), "secret": secret_digest(secret), "shape": secret.shape,
                          "config": config.to_dict()}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()


class Progress:
    """Finished chunks of noise in OUT.partial/, for one run at a time.

    A run holds an exclusive lock on OUT.partial/lock for its whole life, so a second hide writing to the
    same output is refused at once instead of mixing two secrets' chunks. Each chunk is written atomically
    (fsynced, then renamed) and carries the run key, its own position and a SHA-256 of its tensors; a
    chunk that fails any check on load (another run's, truncated, edited, wrong shape or dtype, NaN,
    missing fields) is deleted and solved again. The key file says which run the folder belongs to; if it
    is anything but this run's key in a regular file, every chunk there is discarded.
    """

    def __init__(self, output: Path, key: str):
        self.directory = output.with_name(output.name + ".partial")
        self.key = key
        if existing_kind(self.directory) not in (None, "a directory"):
            raise UserError(f"the resume folder {self.directory} is {existing_kind(self.directory)}; remove it")
        try:
            self.directory.mkdir(exist_ok=True)
            self.lock = os.open(self.directory / "lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        except OSError as error:
            raise UserError(f"cannot use the resume folder {self.directory}: {error.strerror or error}") from None
        try:
            fcntl.flock(self.lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if not self.owns_folder():
                self.discard_all()
            with atomic_output(self.directory / "key") as tmp:
                tmp.write_text(key)
        except BlockingIOError:
            os.close(self.lock)
            raise UserError(f"another hide is writing to {self.directory}; wait for it or choose another -o") from None
        except BaseException:
            os.close(self.lock)  # a failed start must not keep the folder locked (in-process callers go on)
            raise

    def owns_folder(self) -> bool:
        """Whether the folder's key file is a regular file holding this run's key."""
        key_file = self.directory / "key"
        if existing_kind(key_file) != "a file":
            return False
        with open(key_file, "rb") as handle:
            return handle.read(len(self.key) + 1) == self.key.encode()

    def discard_all(self) -> None:
        """Remove everything in the folder but the lock we hold (another run's chunks, a stray key folder)."""
        for entry in self.directory.iterdir():
            if entry.name != "lock":
                remove(entry)

    def path(self, tile: int, chunk: int) -> Path:
        return self.directory / f"tile{tile:04d}_chunk{chunk:05d}.safetensors"

    def stamp(self, tile: int, chunk: int, tensors: dict[str, torch.Tensor]) -> dict[str, str]:
        """What a chunk must carry to be reused: this run, this place, and a digest of exactly these tensors."""
        digest = hashlib.sha256(f"{self.key}/{tile}/{chunk}".encode())
        for name in sorted(tensors):
            value = tensors[name].contiguous().cpu()
            digest.update(f"{name}:{value.dtype}:{tuple(value.shape)}".encode())
            digest.update(value.view(torch.uint8).numpy().tobytes() if value.numel() else b"")
        return {"run_key": self.key, "tile": str(tile), "chunk": str(chunk), "sha256": digest.hexdigest()}

    def load(self, tile: int, chunk: int, shapes: dict[str, tuple[int, ...]] | None = None) -> dict | None:
        """A saved chunk that passes every check (and has exactly `shapes`, when given), else None; a chunk
        that fails is deleted, so it is solved again and rewritten."""
        path = self.path(tile, chunk)
        if existing_kind(path) is None:
            return None
        tensors = self.verified(path, tile, chunk, shapes)
        if tensors is None:
            remove(path)
        return tensors

    def verified(self, path: Path, tile: int, chunk: int, shapes: dict | None) -> dict | None:
        """The chunk's tensors if its stamp, shapes and values are sound; None for anything else."""
        try:
            with safe_open(str(path), framework="pt") as handle:
                metadata = handle.metadata() or {}
                tensors = {name: handle.get_tensor(name) for name in handle.keys()}
        except Exception:  # safetensors raises several types for bad files; any of them means "recompute"
            return None
        if metadata != self.stamp(tile, chunk, tensors):
            return None
        if shapes is not None and {name: tuple(value.shape) for name, value in tensors.items()} != shapes:
            return None
        if any(value.is_floating_point() and not torch.isfinite(value).all() for value in tensors.values()):
            return None
        return tensors

    def save(self, tile: int, chunk: int, tensors: dict) -> None:
        tensors = {k: v.contiguous().cpu() for k, v in tensors.items()}
        with atomic_output(self.path(tile, chunk)) as tmp:
            save_file(tensors, str(tmp), metadata=self.stamp(tile, chunk, tensors))

    def clear(self) -> None:
        """Remove the folder once the bundle is written (the lock is released on leaving the run)."""
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        os.close(self.lock)  # releases the flock, whether the run finished or failed


def remove(entry: Path) -> None:
    """Delete a file, symlink or folder in OUT.partial/ (a folder where a chunk or the key should be)."""
    if existing_kind(entry) == "a directory":
        shutil.rmtree(entry)
    else:
        entry.unlink(missing_ok=True)


def noise_shape(view: SecretView, config: HideConfig) -> tuple[int, int, int]:
    samples = view.n_samples if config.layout == "sample" else 1
    return view.n_rays, samples, view.noise_dims


def chunk_seed(config: HideConfig, tile: int, chunk: int) -> int:
    """The seed of one chunk's solve; chunk −1 seeds the tile's compact basis."""
    return config.seed * 1_000_003 + tile * 10_007 + chunk


def exact_space(view: SecretView, config: HideConfig, k: int, pixels: torch.Tensor) -> NoiseSpace:
    """Where tile k's exact solve looks for noise: the tile's compact basis, or the full float noise."""
    if config.layout == "compact":
        return tile_space(view, pixels, config.compact, config.exact, TORCH_DTYPES[config.dtype],
                          chunk_seed(config, k, -1))
    return NoiseSpace(TORCH_DTYPES[config.dtype])


def stored_noise(space: NoiseSpace, params: torch.Tensor, escaped: torch.Tensor, escape_noise: torch.Tensor,
                 shape: tuple[int, int]) -> dict:
    """What a tile's bundle entry holds for solved params (n, P): the noise (*shape, P) in the storage dtype
    (integer coefficients for a compact space, 0 where a pixel escaped) and the compact frame, with the
    escaped pixels (n,) bool and their float16 noise (n, dims) (zero elsewhere)."""
    if space.basis is None:
        return {"noise": params.reshape(*shape, -1).to(space.storage).cpu().numpy(), "frame": None}
    escapes = escaped.nonzero()[:, 0]
    frame = Frame(basis=space.basis.cpu().numpy(), offset=space.offset.cpu().numpy(), scale=space.scale,
                  escapes=escapes.to(torch.int32).cpu().numpy(),
                  escape_noise=escape_noise[escapes].to(torch.float16).cpu().numpy())
    coefficients = torch.where(escaped[:, None], 0, space.integers(params))
    return {"noise": coefficients.reshape(*shape, -1).cpu().numpy(), "frame": frame}


def solve_chunk(view: SecretView, index: torch.Tensor, pixels: torch.Tensor, space: NoiseSpace, config: HideConfig,
                seed: int) -> dict[str, torch.Tensor]:
    """One chunk's solve, as saved for resume: params (m, P), counts, and for a compact space the pixels it
    could not finish, `escaped` (m,) uint8, solved again in full float16 noise, `escape_noise` (m, dims)
    (zero where not escaped). Compact solves run at most config.compact.max_iters per phase: the few
    pixels its basis cannot reach escape sooner."""
    generator = torch.Generator().manual_seed(seed)
    if space.basis is None:
        result = solve_exact(view, index, pixels, space, config.exact, generator)
        return {"noise": result.params, "counts": torch.tensor(dataclasses.astuple(result.counts))}
    settings = dataclasses.replace(config.exact, max_iters=config.compact.max_iters)
    result = solve_exact(view, index, pixels, space, settings, generator)
    left = (~result.done).nonzero()[:, 0]
    escape_noise = torch.zeros(len(index), view.noise_dims, device=index.device)
    counts = torch.tensor(dataclasses.astuple(result.counts))
    if left.numel():
        full = solve_exact(view, index[left], pixels[left], NoiseSpace(ESCAPE_DTYPE), config.exact, generator)
        escape_noise[left] = full.params
        counts += torch.tensor(dataclasses.astuple(full.counts))
    return {"noise": result.params, "counts": counts, "escaped": (~result.done).to(torch.uint8),
            "escape_noise": escape_noise}


def hide_tile_exact(view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                    progress: Progress, k: int, bar) -> tuple[torch.Tensor, dict, dict]:
    """Solve a tile chunk by chunk (resuming saved chunks). pixels: (n, 3) uint8 -> noise (n, 1, dims)
    float32 as a reveal expands it, counts, and the tile's stored noise (stored_noise)."""
    space = exact_space(view, config, k, pixels)
    n, dims = view.n_rays, view.noise_dims
    params = space.zeros(n, dims, pixels.device)
    escaped = torch.zeros(n, dtype=torch.bool, device=pixels.device)
    escape_noise = torch.zeros(n, dims, device=pixels.device)
    totals = {"iterations": 0, "jacobians": 0, "renders": 0, "restarts": 0}
    for c, start in enumerate(range(0, n, config.chunk_pixels)):
        index = torch.arange(start, min(start + config.chunk_pixels, n), device=pixels.device)
        shapes = {"noise": (len(index), params.shape[1]), "counts": (len(totals),)}
        if space.basis is not None:
            shapes.update(escaped=(len(index),), escape_noise=(len(index), dims))
        saved = progress.load(k, c, shapes)
        if saved is None:
            saved = solve_chunk(view, index, pixels[index], space, config, chunk_seed(config, k, c))
            progress.save(k, c, saved)
        params[index] = saved["noise"].to(params.device)
        if "escaped" in saved:
            escaped[index] = saved["escaped"].bool().to(escaped.device)
            escape_noise[index] = saved["escape_noise"].to(escape_noise.device)
        counts = dict(zip(totals, saved["counts"].tolist()))
        totals = {name: max(value, counts[name]) if name == "iterations" else value + counts[name]
                  for name, value in totals.items()}
        bar.update(len(index))
    noise = torch.where(escaped[:, None, None], escape_noise[:, None, :], space.expand(params))
    prefix = (*shape, 1) if config.layout == "sample" else shape  # the sample layout of a one-sample view
    return noise, {**totals, "escaped": int(escaped.sum())}, stored_noise(space, params, escaped, escape_noise, prefix)


def hide_tile_paper(view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                    progress: Progress, k: int, bar) -> tuple[torch.Tensor, dict, dict]:
    """The paper's optimisation, block after block (each saved, so a hide resumes per block). The tile's
    noise waits on the CPU in the storage dtype, so device memory holds one block. pixels: (n, 3) uint8
    -> noise (n, k, dims), {records: tile quality at each recorded iteration, dead_rays}, stored noise."""
    settings = config.paper
    points = recorded_points(settings)
    clean = survey(view, settings.pass_samples)
    noise = torch.zeros(noise_shape(view, config), dtype=TORCH_DTYPES[config.dtype])
    colors = torch.zeros(len(points), view.n_rays, 3)

    def saved_block(b: int) -> dict | None:
        m = min(settings.block_pixels, view.n_rays - b * settings.block_pixels)
        return progress.load(k, b, {"noise": (m, *noise.shape[1:]), "colors": (len(points), m, 3)})

    for b, block in enumerate(solve_blocks(view, pixels, noise.shape[1], settings, clean, noise.dtype, saved_block)):
        if block.solved:
            progress.save(k, b, {"noise": block.noise, "colors": block.colors})
        noise[block.index.cpu()] = block.noise
        colors[:, block.index.cpu()] = block.colors
        bar.update(block.index.numel())
    target = pixels.cpu().float() / 255.0
    records = [{"iteration": t, "loss": float(((colors[i] - target) ** 2).sum(-1).mean()),
                **quality(colors[i].numpy(), pixels.cpu().numpy(), shape)} for i, t in enumerate(points)]
    stored = noise.reshape(*shape, *noise.shape[1:]) if config.layout == "sample" else noise.reshape(*shape, -1)
    return noise, {"records": records, "dead_rays": int((~clean.alive).sum())}, {"noise": stored.numpy(), "frame": None}


def quality(colors: np.ndarray, pixels: np.ndarray, shape: tuple[int, int]) -> dict:
    """Metrics of a rendered tile against its 8-bit target. colors: (n, 3) float, pixels: (n, 3) uint8."""
    image, target = colors.reshape(*shape, 3), pixels.reshape(*shape, 3)
    got = to_uint8(image)
    return {
        "exact_fraction": exact_fraction(got, target),
        "max_error": int(np.abs(got.astype(np.int16) - target).max()),
        "psnr": psnr(got / 255.0, target / 255.0),
        "ssim": ssim(got / 255.0, target / 255.0) if min(shape) >= 11 else None,
    }


@contextlib.contextmanager
def solver_threads(config: HideConfig, device: torch.device):
    """The exact method solves with one torch thread on a CPU. Its Levenberg–Marquardt loop is thousands
    of small ops; with torch's OpenMP pool of one thread per core, every op is a parallel region whose
    idle threads spin, and on a machine whose cores are shared that spinning took the solver's own CPU
    (README, "Predictable speed": a 64×64 hide 25–54 s instead of ~2 s beside other busy processes).
    One thread measured 1.35 s quiet against 1.1 s for two, ~2 s beside two busy loops against 4.6–6.7
    s, and makes the bundle's bytes independent of the machine's core count."""
    if config.method != "exact" or device.type != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(EXACT_CPU_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def hide(scene: Scene, secret: np.ndarray, output: Path, config: HideConfig, device: torch.device,
         force: bool = False, show_progress: bool = True, payload: dict | None = None) -> dict:
    """Hide `secret` (H, W, 3) uint8 in the scene; write the bundle to `output`; return the report.
    payload: the bundle's payload object when the secret carries one (train.payload), else None."""
    output = check_output_path(output, force=force)
    checked_image_size(secret.shape[1], secret.shape[0], "the secret image")  # what a bundle may hold
    if config.layout == "ray" and config.n_samples > MAX_RAY_LAYOUT_SAMPLES:
        raise UserError(f"the ray layout serves at most {MAX_RAY_LAYOUT_SAMPLES} samples per ray, "
                        f"not {config.n_samples}")
    hide_plan = plan(scene, secret, config)
    scene.to(device)
    field = scene.render_field
    with Progress(output, run_key(scene, secret, config)) as progress, solver_threads(config, device):
        solve = hide_tile_exact if config.method == "exact" else hide_tile_paper
        tiles, reports = [], []
        started = time.perf_counter()
        bar = tqdm(total=secret.shape[0] * secret.shape[1], unit="px", desc=f"hide ({config.method})",
                   disable=not show_progress, dynamic_ncols=True)
        for k, tile in enumerate(hide_plan.tiles):
            tile_start = time.perf_counter()
            x0, y0, w, h = tile.rect
            view = SecretView(scene.fields()[tile.network], tile, scene.config.render, device)
            pixels = torch.tensor(secret[y0:y0 + h, x0:x0 + w].reshape(-1, 3), device=device)
            noise, counts, stored = solve(view, pixels, (h, w), config, progress, k, bar)
            with torch.no_grad():
                colors = torch.cat([view.render(torch.arange(part.start, part.stop, device=device),
                                                noise[part].to(device, torch.float32))
                                    for part in pass_slices(view.n_rays, view.n_samples, config.paper.pass_samples)])
            tiles.append(dataclasses.replace(tile, **stored))
            reports.append({"rect": list(tile.rect), "view": tile.view,
                            **quality(colors.cpu().numpy(), pixels.cpu().numpy(), (h, w)),
                            **counts, "seconds": round(time.perf_counter() - tile_start, 2)})
        bar.close()
        bundle = Bundle(model_fingerprint=scene.fingerprint(), width=secret.shape[1], height=secret.shape[0],
                        secret_sha256=secret_digest(secret), layout=config.layout,
                        noise_dims=field.config.noise_dims, dtype=config.dtype, tiles=tuple(tiles),
                        extra={"method": config.method, "noisenerf": noisenerf.__version__,
                               "config": config.to_dict()}, payload=payload,
                        coefficients=config.compact.coefficients if config.layout == "compact" else None)
        bundle.save(output)
        progress.clear()
    n_pixels = secret.shape[0] * secret.shape[1]
    exact_pixels = sum(r["exact_fraction"] * r["rect"][2] * r["rect"][3] for r in reports)
    return {
        "bundle": str(output), "method": config.method, "layout": config.layout, "dtype": config.dtype,
        "width": secret.shape[1], "height": secret.shape[0], "tiles": reports,
        "exact_fraction": exact_pixels / n_pixels, "exact": all(r["exact_fraction"] == 1.0 for r in reports),
        "bundle_bytes": output.stat().st_size, "bytes_per_pixel": output.stat().st_size / n_pixels,
        "seconds": round(time.perf_counter() - started, 2),
    }
