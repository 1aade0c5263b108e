"""The embedded default scene and secret: generated here, so the project ships no third-party pixels.

`write_procedural_dataset` ray-traces a small still life (a checkered slab, four spheres, a box) inside
[-1, 1]^3 exactly (analytic ray–primitive intersection, Lambert + ambient shading from a fixed sun with
hard shadows, 3×3 supersampling for anti-aliased alpha edges) from cameras on the upper hemisphere, and
writes it in the NeRF-Synthetic format, or as a phone capture seen through a distorting lens (nerfstudio's
transforms.json). `procedural_secret` draws a picture to hide in the demo.
Everything is numpy and deterministic for a seed: the same call writes byte-identical files.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.camera import Camera, pixel_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import check_output_directory, write_json
from noisenerf.runtime.images import composite_over, write_image
from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.lens import COEFFICIENTS, Lens
from noisenerf.train.scene.datasets import CAPTURE_FILE, matrix_rows

FOV_X = 0.6911112070083618  # lego's camera_angle_x
CAMERA_RADIUS = 4.0
CAMERA_HEIGHTS = (0.1, 0.95)  # range of z / radius: above the slab, short of the pole where "up" degenerates
SUPERSAMPLE = 3  # rays per pixel along each axis
AMBIENT = 0.3
LIGHT = np.array([0.45, -0.35, 1.0]) / np.linalg.norm([0.45, -0.35, 1.0])  # towards the sun
EPSILON = 1e-6  # nearest accepted hit distance, and how far shadow rays start off the surface
CHECKER_CELL = 0.25  # slab checker square size; the slab edges (±0.95) fall inside squares, not on seams
SPLITS = ("train", "val", "test")
FORMATS = ("blender", "capture")
CAPTURE_RADIUS = 1.8  # closer than the NeRF-Synthetic views, as a phone walks round an object
CAPTURE_FOCAL = 0.55  # fl_x / width: a phone's wide angle (about 85° across), where the distortion moves pixels
CAPTURE_LENS = {"k1": -0.05, "k2": 0.01, "p1": 0.002, "p2": -0.001}  # OpenCV's model: mild barrel, a tilted lens
# the shipped demo scene, fitted on this dataset (docs/usage.md, "The demo scene"); package data of noisenerf.train
DEMO_SCENE = Path(__file__).resolve().parents[1] / "assets" / "demo_scene"


def unit(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3) of length 1."""
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    albedo: tuple[float, float, float]

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit in front of the origins (inf for a miss) and the surface normal there.
        origins, dirs (unit): (n, 3) -> t (n,), normals (n, 3)."""
        offset = origins - np.asarray(self.center)
        b = np.einsum("ij,ij->i", offset, dirs)
        discriminant = b * b - (np.einsum("ij,ij->i", offset, offset) - self.radius ** 2)
        t = -b - np.sqrt(np.maximum(discriminant, 0.0))
        t = np.where((discriminant >= 0) & (t > EPSILON), t, np.inf)
        normals = (offset + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs) / self.radius
        return t, normals

    def albedo_at(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) -> (n, 3)."""
        return np.broadcast_to(np.asarray(self.albedo), points.shape)


@dataclass(frozen=True)
class Box:
    """Axis-aligned; with `checker` set, squares alternate between `albedo` and `checker` in x and y."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]
    albedo: tuple[float, float, float]
    checker: tuple[float, float, float] | None = None

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slab method. origins, dirs: (n, 3) -> t (n,), normals (n, 3) of the face entered."""
        safe = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)  # keeps axis-parallel rays finite
        t_low, t_high = (np.asarray(self.low) - origins) / safe, (np.asarray(self.high) - origins) / safe
        t_in, t_out = np.minimum(t_low, t_high), np.maximum(t_low, t_high)
        entry, exit_ = t_in.max(axis=1), t_out.min(axis=1)
        axis = t_in.argmax(axis=1)
        t = np.where((entry <= exit_) & (entry > EPSILON), entry, np.inf)
        rows = np.arange(len(origins))
        normals = np.zeros_like(origins)
        normals[rows, axis] = -np.sign(safe[rows, axis])
        return t, normals

    def albedo_at(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) -> (n, 3)."""
        if self.checker is None:
            return np.broadcast_to(np.asarray(self.albedo), points.shape)
        odd = np.floor(points[:, :2] / CHECKER_CELL).sum(axis=1) % 2 == 1
        return np.where(odd[:, None], np.asarray(self.checker), np.asarray(self.albedo))


FLOOR = -0.35  # top of the slab, where the objects rest
PRIMITIVES = (
    Box((-0.95, -0.95, FLOOR - 0.15), (0.95, 0.95, FLOOR), (0.88, 0.86, 0.8), checker=(0.3, 0.32, 0.38)),
    Sphere((-0.35, -0.3, FLOOR + 0.35), 0.35, (0.85, 0.2, 0.15)),
    Sphere((0.45, -0.35, FLOOR + 0.25), 0.25, (0.2, 0.7, 0.3)),
    Sphere((0.15, 0.45, FLOOR + 0.4), 0.4, (0.2, 0.35, 0.85)),
    Sphere((0.75, 0.35, FLOOR + 0.15), 0.15, (0.95, 0.8, 0.2)),
    Box((-0.9, 0.0, FLOOR), (-0.55, 0.35, FLOOR + 0.6), (0.6, 0.3, 0.7)),
)


def trace(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit over all primitives. (n, 3), (n, 3) -> t (n,) (inf: miss), normals (n, 3), primitive (n,)."""
    hits = [primitive.intersect(origins, dirs) for primitive in PRIMITIVES]
    ts = np.stack([t for t, _ in hits])
    nearest = ts.argmin(axis=0)
    rows = np.arange(len(origins))
    return ts[nearest, rows], np.stack([n for _, n in hits])[nearest, rows], nearest


def shade(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lambert + ambient colour of each ray's hit, with sun shadows. (n, 3), (n, 3) -> rgb (n, 3), hit (n,)."""
    t, normals, nearest = trace(origins, dirs)
    hit = np.isfinite(t)
    points = origins + np.where(hit, t, 0.0)[:, None] * dirs
    albedo = np.zeros_like(points)
    for index, primitive in enumerate(PRIMITIVES):
        mask = hit & (nearest == index)
        albedo[mask] = primitive.albedo_at(points[mask])
    lambert = np.clip(normals @ LIGHT, 0.0, None) * hit
    lit = lambert > 0
    shadow_t, _, _ = trace(points[lit] + EPSILON * normals[lit], np.broadcast_to(LIGHT, (int(lit.sum()), 3)))
    lambert[lit] *= ~np.isfinite(shadow_t)
    return albedo * (AMBIENT + (1.0 - AMBIENT) * lambert)[:, None], hit


def render_rgba(camera: Camera) -> np.ndarray:
    """A view with straight alpha (the covered fraction of each pixel), seen through the camera's lens where it
    has one. -> (height, width, 4) float64 in [0, 1]."""
    offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE
    shape = (camera.height, camera.width, SUPERSAMPLE, SUPERSAMPLE)
    px = np.broadcast_to(np.arange(camera.width)[None, :, None, None] + offsets[None, None, None, :], shape).ravel()
    py = np.broadcast_to(np.arange(camera.height)[:, None, None, None] + offsets[None, None, :, None], shape).ravel()
    origins, dirs = pixel_rays(camera, px, py)
    rgb, hit = shade(origins.astype(np.float64), unit(dirs.astype(np.float64)))
    per_pixel = SUPERSAMPLE * SUPERSAMPLE
    rgb = rgb.reshape(camera.height, camera.width, per_pixel, 3).sum(axis=2)
    hits = hit.reshape(camera.height, camera.width, per_pixel).sum(axis=2)
    colour = rgb / np.maximum(hits, 1)[..., None]
    return np.concatenate([colour, (hits / per_pixel)[..., None]], axis=-1)


def look_at_origin(eye: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world at `eye` looking at the origin, world +z up. (3,) -> (4, 4)."""
    back = unit(eye)
    right = unit(np.cross([0.0, 0.0, 1.0], back))
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


def camera_positions(count: int, rng: np.random.Generator, radius: float = CAMERA_RADIUS) -> np.ndarray:
    """Uniform by area on the upper hemisphere band CAMERA_HEIGHTS of `radius`. -> (count, 3)."""
    azimuth = rng.uniform(0.0, 2.0 * np.pi, count)
    z = rng.uniform(*CAMERA_HEIGHTS, count)
    ring = np.sqrt(1.0 - z * z)
    return radius * np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def write_frame(folder: Path, split: str, index: int, c2w: np.ndarray, size: int) -> dict:
    """Render and write {split}/r_{index}.png; -> its NeRF-Synthetic `frames` entry."""
    rgba = render_rgba(Camera.from_fov(c2w, size, size, FOV_X))
    write_image(folder / split / f"r_{index}.png", to_uint8(rgba))
    return {"file_path": f"./{split}/r_{index}", "rotation": 0.0, "transform_matrix": c2w.tolist()}


def capture_intrinsics(width: int, height: int) -> dict:
    """A capture's shared intrinsics, as a calibration finds them: pixels not quite square, the principal
    point off the centre."""
    focal = CAPTURE_FOCAL * width
    return {"w": width, "h": height, "fl_x": focal, "fl_y": 1.01 * focal, "cx": 0.5 * width + 0.37,
            "cy": 0.5 * height - 0.29}


def write_capture(folder: Path, count: int, size: int, rng: np.random.Generator) -> None:
    """`count` views through the lens CAPTURE_LENS as RGB photos over white (a photo has no alpha),
    images/frame_00001.png on (size × ¾·size), and one transforms.json as nerfstudio writes it: camera_model
    OPENCV, shared intrinsics that the second frame overrides (fl_x, cx), frames in shuffled order."""
    shared = capture_intrinsics(size, size * 3 // 4)
    lens = Lens("opencv", tuple(float(CAPTURE_LENS.get(key, 0.0)) for key in COEFFICIENTS))
    (folder / "images").mkdir()
    frames = []
    for k, eye in enumerate(camera_positions(count, rng, CAPTURE_RADIUS)):
        own = {"fl_x": 1.1 * shared["fl_x"], "cx": shared["cx"] - 0.6} if k == 1 else {}
        stated, c2w, name = {**shared, **own}, look_at_origin(eye), f"images/frame_{k + 1:05d}.png"
        camera = Camera(matrix_rows(c2w), stated["w"], stated["h"], stated["fl_x"], stated["fl_y"], stated["cx"],
                        stated["cy"], lens)
        write_image(folder / name, to_uint8(composite_over(render_rgba(camera), (1.0, 1.0, 1.0))))
        frames.append({"file_path": name, "transform_matrix": c2w.tolist(), **own})
    write_json(folder / CAPTURE_FILE, {"camera_model": "OPENCV", **shared, **CAPTURE_LENS,
                                       "frames": [frames[k] for k in rng.permutation(count)]})


@contextlib.contextmanager
def staging_folder(out_dir: Path):
    """Yield a hidden sibling folder that is renamed to `out_dir` only when the block succeeds."""
    if check_output_directory(out_dir).exists() and any(out_dir.iterdir()):
        raise UserError(f"output exists and is not an empty folder: {out_dir}")
    staging = out_dir.parent / f".{out_dir.name}.{secrets.token_hex(4)}.tmp"
    staging.mkdir()
    try:
        yield staging
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def write_procedural_dataset(out_dir, size: int = 64, n_train: int = 40, n_val: int = 4, n_test: int = 8,
                             seed: int = 0, format: str = "blender") -> Path:
    """Write the still life as a NeRF-Synthetic dataset: {train,val,test}/r_k.png (size×size RGBA, alpha 0
    off the objects) and transforms_{train,val,test}.json; cameras at radius 4 on the upper hemisphere,
    drawn from `seed`. format="capture": n_train + n_val + n_test views in one transforms.json instead
    (`write_capture`; its loader holds out its own test views). The folder appears whole or not at all; it
    must not exist (or be empty)."""
    if size < 8:
        raise UserError(f"procedural dataset size must be at least 8 px, got {size}")
    if n_train < 1 or n_val < 0 or n_test < 0:
        raise UserError(f"need at least one train view and no negative counts, got {n_train}/{n_val}/{n_test}")
    if format not in FORMATS:
        raise UserError(f"unknown procedural dataset format {format!r:.40} (expected one of {', '.join(FORMATS)})")
    out_dir = Path(out_dir)
    rng = np.random.default_rng(seed)
    with staging_folder(out_dir) as staging:
        if format == "capture":
            write_capture(staging, n_train + n_val + n_test, size, rng)
        else:
            for split, count in zip(SPLITS, (n_train, n_val, n_test)):
                (staging / split).mkdir()
                frames = [write_frame(staging, split, k, look_at_origin(eye), size)
                          for k, eye in enumerate(camera_positions(count, rng))]
                write_json(staging / f"transforms_{split}.json", {"camera_angle_x": FOV_X, "frames": frames})
    return out_dir


def hsv_to_rgb(hue: np.ndarray, saturation: float, value: np.ndarray) -> np.ndarray:
    """hue in [0, 1), saturation, value: broadcastable (H, W) -> (H, W, 3) in [0, 1]."""
    channels = []
    for n in (5.0, 3.0, 1.0):
        k = (n + hue * 6.0) % 6.0
        channels.append(value - value * saturation * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0))
    return np.stack(channels, axis=-1)


def procedural_secret(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A picture to hide: a hue sweep, inverted concentric rings, random hard-edged discs and squares, and
    black/white corner squares so it spans 0..255. Resolution-independent layout. -> (height, width, 3) uint8."""
    rng = np.random.default_rng(seed)
    unit_px = min(width, height)
    y, x = (np.mgrid[:height, :width] + 0.5) / unit_px
    image = hsv_to_rgb((0.6 * x + 0.25 * y + rng.uniform()) % 1.0, 0.8, 0.55 + 0.45 * np.cos(3.0 * y) ** 2)
    centre = rng.uniform(0.3, 0.7, 2) * (width / unit_px, height / unit_px)
    distance = np.hypot(x - centre[0], y - centre[1])
    rings = (distance < 0.4) & (np.floor(distance * 12.0) % 2 == 0)
    image = np.where(rings[..., None], 1.0 - image, image)
    for _ in range(6):
        cx, cy = rng.uniform(0.0, 1.0, 2) * (width / unit_px, height / unit_px)
        half = rng.uniform(0.04, 0.12)
        disc = rng.uniform() < 0.5
        shape = np.hypot(x - cx, y - cy) < half if disc else (np.abs(x - cx) < half) & (np.abs(y - cy) < half)
        image = np.where(shape[..., None], rng.uniform(0.0, 1.0, 3), image)
    corner = 0.12
    image[(x < corner) & (y < corner)] = 0.0
    image[(x > width / unit_px - corner) & (y > height / unit_px - corner)] = 1.0
    return to_uint8(image)
