"""What one `noisenerf bench` run measures. A leaf: it imports no other bench module, so that every one
of them can import it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BenchConfig:
    """What one `noisenerf bench` run measures (saved at the top of the report)."""

    scene: str
    secret: str
    data: str | None = None  # dataset whose test views the skipping experiment renders
    photos: tuple[str, ...] = ()  # secrets hidden at native size in the photos experiment
    view: int = 0
    small_width: int = 48  # secret width for the curves that include the paper's method on a CPU
    paper_samples: int = 64
    paper_iters: int = 300  # the paper's iteration count (lower only to test the bench quickly)
    paper_recipe: str = "noisenerf"
    paper_width: int | None = None  # paper-quality secrets (square): None = 400 (the paper's) on CUDA, small_width on CPU
    paper_photos: int = 3
    # paper_quality and paper_changes: (scene directory, view) pairs, each scene fitted as the README says; (): the
    # bench's scene at its view
    paper_scenes: tuple[tuple[str, int], ...] = ()
    paper_secrets: tuple[str, ...] = ()  # the photos they hide; (): the first paper_photos of photos
    paper_changes_secrets: int | None = None  # paper_changes: each change switched off on the first this many (None: all)
    speed_width: int = 64  # the paper_speed experiment's secrets (square), hidden with and without skipping
    ablation_samples: int = 64
    ablation_width: int | None = None  # None = 100 (the authors' secret) on CUDA, small_width on CPU
    device: str = "cpu"  # where the paper-mode and error-vs-time experiments run (cpu or cuda)
    twok_size: int = 2048
    twok_tile: int = 512
    twok_rows: int = 1  # tile rows of the 2048² secret hidden (of 4); the rest is extrapolated
    cluster_size: int = 512  # the cluster experiment's multi-tile secret (square), in cluster_tile tiles
    cluster_tile: int = 128
    cluster_photo: tuple[int, int] = (4032, 3024)  # (width, height): a phone camera's 12 MP, hidden through Ray
    big_secret: tuple[int, int] = (7680, 4320)  # (width, height): an 8K secret, hidden and revealed by the CLI tools
    browser_size: int = 2048  # the browser experiment's tiled secret (square, twok_tile tiles), hidden whole
    browser_repeats: int = 5  # most runs of each reveal, both sides (median; a 2048² one runs once)
    threads: tuple[int, ...] = (1, 2)
    payload_bytes: int = 1 << 20  # the file the payload experiment hides, plain and sealed (random bytes)
    masking_photos: int = 3  # photos (the first of `photos`) the masking experiment hides at two views
    masking_width: int = 128  # their width there
    margin_photos: int = 4  # photos (the first of `photos`) the margins experiment hides
    margin_width: int = 64  # their width there
    margin_views: int = 3  # the views it hides them at, spread over the cameras (never the bench's `view`)
    junk_bytes: int = 1 << 30  # the reliability experiment's files of junk (zeros, random) given as a model, a bundle
    views: int = 8  # views spread around the scene for the per-view hide times
    view_photos: int = 5  # photos (the first of `photos`) hidden at each of those views
    view_width: int | None = 128  # their width there (None: native; 8 × 5 native photos take ~15 min on 2 cores)
    contention_width: int = 256  # the contention experiment's secret: several chunks, so the hide's workers take part
    coverage_size: int = 24  # the coverage experiment's hard secrets (square): 10 of them at every camera
    fields_resolution: int = 200  # px wide: the fields experiment fits each kind on `data` at this width
    fields_minutes: float = 15.0  # each kind's fit, in training minutes
    fields_curve_seconds: float = 60.0  # a test-PSNR point every this many seconds of it
    fields_presets: tuple[str, ...] = ("small", "hashgrid", "nerfacto")  # the fit presets it compares
    nerfstudio_run: str | None = None  # the nerfstudio experiment's nerfacto run directory
    nerfstudio_data: str | None = None  # its dataset (transforms.json)
    nerfstudio_golden: str | None = None  # tools/nerfstudio_goldens.py's folder for that run: nerfstudio's renders
    nerfstudio_width: int = 48  # the photos hidden in it (its cameras may be small), and in the ingp experiment's
    ingp_snapshot: str | None = None  # the ingp experiment's Instant-NGP snapshot (.ingp, .msgpack)
    experiments: tuple[str, ...] | None = None  # --only's names; None: every experiment (registry.selected)
    seed: int = 0
