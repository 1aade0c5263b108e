"""Scene datasets: NeRF-Synthetic (`transforms_*.json`), LLFF (`poses_bounds.npy` + `images_N/`) and captures
(one `transforms.json`, as Instant-NGP's colmap2nerf.py and nerfstudio's ns-process-data write it, read by
`train.scene.captures`, which the nerfstudio import shares).

All load to one `Dataset`: images composited on a background, one `Camera` per image (OpenGL c2w, at the
loaded resolution, a capture's with its lens: runtime.lens), splits, the ray interval, for forward-facing LLFF
scenes nerf-pytorch's NDC space; `view_rays` gives a view's rays as its photo saw them.
LLFF poses follow nerf-pytorch's `load_llff_data(factor, recenter=True, bd_factor=.75, spherify=False)`
operation for operation (float32), so imported nerf-pytorch checkpoints see the cameras they were trained on.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.camera import Camera, NDCSpace, camera_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import read_json
from noisenerf.runtime.images import composite_over, image_shape, read_image, resize_image
from noisenerf.train.scene.captures import CAPTURE_FILE, FISHEYE_MODEL, CaptureFrame, frame_file_and_pose, read_capture

BLENDER_SPLITS = ("train", "val", "test")
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
BLENDER_AABB = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
LLFF_AABB = (-1.5, -1.5, -1.0, 1.5, 1.5, 1.0)  # in NDC space: x, y in [-1, 1], z in [-1, 1]
LLFF_BD_FACTOR = 0.75
LLFF_HOLD = 8  # nerf-pytorch's llffhold: every 8th view is held out
LLFF_DEFAULT_FACTOR = 8
LLFF_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
CAPTURE_NEAR = 0.05  # in normalised units, where the cameras span [-1, 1]


@dataclass(frozen=True)
class Dataset:
    kind: str  # "blender" | "llff" | "capture"
    images: np.ndarray | None  # (n, H, W, 3) float32 composited on `background`; None if loaded without images
    cameras: tuple[Camera, ...]  # one per image, at the loaded resolution
    splits: dict[str, tuple[int, ...]]  # "train", "val", "test" -> indices into images / cameras
    near: float  # ray interval in t (NDC scenes: 0, 1)
    far: float
    ndc: NDCSpace | None  # forward-facing scenes only
    background: tuple[float, float, float]
    aabb: tuple[float, ...]  # (xmin, ymin, zmin, xmax, ymax, zmax) in the field's space
    alphas: np.ndarray | None = None  # (n, H, W) float32 coverage of RGBA datasets (space carving); else None
    skipped: tuple[str, ...] = ()  # a capture's frames left out, as its file names them: their images are missing


def load_dataset(data_dir, resolution: int | None = None, with_images: bool = True,
                 background=(1.0, 1.0, 1.0), factor: int | None = None) -> Dataset:
    """Load a NeRF-Synthetic, LLFF or capture scene folder.

    resolution: output width in pixels (height keeps the aspect ratio, rounded half up); None = as stored
    (NeRF-Synthetic, captures) or images_8 (LLFF). factor: LLFF only, load images_{factor} (nerf-pytorch's --factor).
    with_images=False reads only image headers (sizes) and leaves `images` None.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise UserError(f"dataset folder not found: {data_dir}")
    if resolution is not None and resolution < 1:
        raise UserError(f"resolution must be a positive width in pixels, got {resolution}")
    background = tuple(float(v) for v in background)
    if len(background) != 3:
        raise UserError(f"background must be three values (RGB), got {background}")
    if (data_dir / "transforms_train.json").is_file():
        return load_blender(data_dir, resolution, with_images, background)
    if (data_dir / "poses_bounds.npy").is_file():
        return load_llff(data_dir, resolution, with_images, background, factor)
    if (data_dir / CAPTURE_FILE).is_file():
        return load_capture(data_dir, resolution, with_images, background)
    raise UserError(f"{data_dir} is not a dataset: expected transforms_train.json (NeRF-Synthetic), "
                    f"poses_bounds.npy with images_N/ (LLFF) or {CAPTURE_FILE} (a capture)")


AT_ORIGIN = tuple(tuple(float(i == j) for j in range(4)) for i in range(4))  # identity c2w: camera space


@functools.lru_cache(maxsize=2)  # one lens per capture as a rule: inverting it is the cost, rotating it is not
def lens_directions(lens_camera: Camera, pixel_center: float) -> np.ndarray:
    """Camera-space directions of every pixel of a camera at AT_ORIGIN, row-major, read-only. -> (n, 3) float32."""
    directions = camera_rays(lens_camera, pixel_center)[1]
    directions.setflags(write=False)
    return directions


def view_rays(camera: Camera, pixel_center: float) -> tuple[np.ndarray, np.ndarray]:
    """World rays of a view's pixels as its photo saw them, through its camera's lens, row-major: the same values
    as runtime.camera.camera_rays (its directions times R, in float32), the lens inverted once per lens and size.
    -> rays_o, rays_d: (width · height, 3) float32."""
    if camera.lens is None:
        return camera_rays(camera, pixel_center)
    directions = lens_directions(dataclasses.replace(camera, c2w=AT_ORIGIN), float(pixel_center))
    c2w = camera.matrix()
    return np.broadcast_to(c2w[:3, 3], directions.shape).astype(np.float32), directions @ c2w[:3, :3].T


# ---- shared ------------------------------------------------------------------------------------

def scaled_size(width: int, height: int, resolution: int | None) -> tuple[int, int]:
    """(width, height) at `resolution` px wide, aspect kept, height rounded half up; None keeps the size."""
    if resolution is None:
        return width, height
    if resolution > width:
        raise UserError(f"resolution {resolution} is larger than the images ({width} px wide)")
    return resolution, max(1, math.floor(height * resolution / width + 0.5))


def common_shape(paths: list[Path], allowed_channels: tuple[int, ...]) -> tuple[int, int]:
    """(height, width) shared by all images, from their headers; UserError on a mismatch or bad channels."""
    shapes = [image_shape(path) for path in paths]
    for path, (height, width, channels) in zip(paths, shapes):
        if channels not in allowed_channels:
            raise UserError(f"image {path} has {channels} channels; expected "
                            f"{' or '.join(str(c) for c in allowed_channels)}")
        if (height, width) != shapes[0][:2]:
            raise UserError(f"image {path} is {width}x{height}, but {paths[0]} is {shapes[0][1]}x{shapes[0][0]}")
    return shapes[0][:2]


def load_rgb(path: Path, size: tuple[int, int], background: tuple[float, float, float],
             composite: bool) -> tuple[np.ndarray, np.ndarray]:
    """One image as RGB at size (width, height): alpha composited (or dropped), area-downscaled, and its
    alpha coverage (ones without alpha). -> (height, width, 3), (height, width) float32."""
    pixels = read_image(path)
    if not np.isfinite(pixels).all():
        raise UserError(f"image {path} holds NaN or infinite values; a NeRF cannot be fitted to them")
    alpha = pixels[..., 3:] if pixels.shape[-1] == 4 else np.ones_like(pixels[..., :1])
    if pixels.shape[-1] == 4:
        pixels = composite_over(pixels, background) if composite else pixels[..., :3]
    if pixels.shape[1::-1] != size:
        pixels, alpha = resize_image(pixels, *size), resize_image(alpha, *size)
    return pixels, alpha[..., 0]


def load_images(paths: list[Path], size: tuple[int, int], background: tuple[float, float, float],
                composite: bool) -> tuple[np.ndarray, np.ndarray]:
    """Images (n, height, width, 3) and alpha coverages (n, height, width), float32."""
    images = np.empty((len(paths), size[1], size[0], 3), dtype=np.float32)
    alphas = np.empty((len(paths), size[1], size[0]), dtype=np.float32)
    for k, path in enumerate(paths):
        images[k], alphas[k] = load_rgb(path, size, background, composite)
    return images, alphas


# ---- NeRF-Synthetic ------------------------------------------------------------------------------

@dataclass(frozen=True)
class BlenderFrame:
    path: Path
    c2w: np.ndarray  # (4, 4) OpenGL camera-to-world
    fov_x: float


def parse_frame(data_dir: Path, frame, fov_x: float, where: str) -> BlenderFrame:
    """One entry of a NeRF-Synthetic `frames`; UserError naming `where` when malformed."""
    return BlenderFrame(*frame_file_and_pose(data_dir, frame, where), fov_x)


def read_blender_split(data_dir: Path, split: str) -> list[BlenderFrame]:
    """Frames of transforms_{split}.json; a missing val/test file is an empty split."""
    path = data_dir / f"transforms_{split}.json"
    if split != "train" and not path.is_file():
        return []
    meta = read_json(path, f"transforms_{split}.json")
    fov_x = meta.get("camera_angle_x")
    if not isinstance(fov_x, (int, float)) or not 0 < fov_x < math.pi:
        raise UserError(f"{path}: 'camera_angle_x' must be an angle in radians in (0, pi)")
    frames = meta.get("frames")
    if not isinstance(frames, list) or (split == "train" and not frames):
        raise UserError(f"{path}: 'frames' must be a list of frames (at least one for train)")
    return [parse_frame(data_dir, frame, float(fov_x), f"{path} frame {k}") for k, frame in enumerate(frames)]


def load_blender(data_dir: Path, resolution: int | None, with_images: bool,
                 background: tuple[float, float, float]) -> Dataset:
    """NeRF-Synthetic: c2w used as is, RGBA composited over `background` with straight alpha, then
    area-downscaled; splits train, val, test concatenated in that order."""
    per_split = {split: read_blender_split(data_dir, split) for split in BLENDER_SPLITS}
    frames = [frame for split in BLENDER_SPLITS for frame in per_split[split]]
    paths = [frame.path for frame in frames]
    height, width = common_shape(paths, (3, 4))
    size = scaled_size(width, height, resolution)
    cameras = tuple(Camera.from_fov(frame.c2w, *size, frame.fov_x) for frame in frames)
    counts = np.cumsum([0] + [len(per_split[split]) for split in BLENDER_SPLITS])
    splits = {split: tuple(range(counts[k], counts[k + 1])) for k, split in enumerate(BLENDER_SPLITS)}
    images, alphas = load_images(paths, size, background, composite=True) if with_images else (None, None)
    return Dataset("blender", images, cameras, splits, BLENDER_NEAR, BLENDER_FAR, None, background, BLENDER_AABB,
                   alphas)


# ---- LLFF ----------------------------------------------------------------------------------------

def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """poses_bounds.npy (n, 17) -> LLFF poses (n, 3, 5) [down, right, back, t | h, w, f] and bounds (n, 2)."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise UserError(f"cannot read {path}: {error}") from None
    if array.ndim != 2 or array.shape[1] != 17 or len(array) == 0 or not np.issubdtype(array.dtype, np.number):
        raise UserError(f"{path} must hold an (n, 17) number array, got {array.shape} {array.dtype}")
    if not np.isfinite(array).all():
        raise UserError(f"{path} holds non-finite values")
    if (array[:, 14] <= 0).any() or (array[:, 15:] <= 0).any():
        raise UserError(f"{path}: focal lengths and depth bounds must be positive")
    return array[:, :15].reshape(-1, 3, 5), array[:, 15:]


def to_opengl(poses: np.ndarray) -> np.ndarray:
    """LLFF's [down, right, back] axes to [right, up, back]. (n, 3, 5) -> (n, 3, 5), float32 as nerf-pytorch."""
    return np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:]], axis=2).astype(np.float32)


def normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def view_matrix(z: np.ndarray, up: np.ndarray, position: np.ndarray) -> np.ndarray:
    """nerf-pytorch's viewmatrix: orthonormal axes from a back vector and an up hint. -> (3, 4)."""
    z = normalize(z)
    x = normalize(np.cross(up, z))
    return np.stack([x, normalize(np.cross(z, x)), z, position], axis=1)


def with_bottom_row(matrices: np.ndarray) -> np.ndarray:
    """(..., 3, 4) -> (..., 4, 4) float64: nerf-pytorch's float64 [0, 0, 0, 1] row promotes float32 poses."""
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), matrices.shape[:-2] + (1, 4))
    return np.concatenate([matrices, bottom], axis=-2)


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """nerf-pytorch's poses_avg without hwf: mean centre, summed back and up axes. (n, 3, 4) -> (3, 4)."""
    return view_matrix(c2w[:, :, 2].sum(0), c2w[:, :, 1].sum(0), c2w[:, :, 3].mean(0))


def recenter(c2w: np.ndarray) -> np.ndarray:
    """nerf-pytorch's recenter_poses: every pose in the average pose's frame, computed in float64 as there.
    (n, 3, 4) float32 -> (n, 4, 4) float32."""
    return (np.linalg.inv(with_bottom_row(average_pose(c2w))) @ with_bottom_row(c2w)).astype(np.float32)


def llff_c2w(poses: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """LLFF poses (n, 3, 5) and bounds (n, 2) -> recentred OpenGL c2w (n, 4, 4) float32, scaled so the
    nearest bound is 1/bd_factor."""
    c2w = to_opengl(poses)[:, :, :4]
    if not np.all(np.abs(np.linalg.det(c2w[:, :, :3].astype(np.float64))) > 1e-6):
        raise UserError("poses_bounds.npy has degenerate poses (a rotation that is not invertible)")
    scale = 1.0 / (bounds.astype(np.float32).min() * LLFF_BD_FACTOR)
    c2w[:, :, 3] *= scale
    return recenter(c2w)


def matrix_rows(c2w: np.ndarray) -> tuple[tuple[float, ...], ...]:
    """A (4, 4) matrix as a Camera's c2w: nested tuples of Python floats."""
    return tuple(tuple(float(v) for v in row) for row in c2w)


def pinhole(c2w: np.ndarray, width: int, height: int, focal: float) -> Camera:
    """Square pixels, principal point at the image centre (nerf-pytorch's K). c2w: (4, 4)."""
    return Camera(matrix_rows(c2w), width, height, focal, focal, 0.5 * width, 0.5 * height)


def llff_folders(data_dir: Path) -> dict[int, Path]:
    """Downscale factor -> image folder: images/ is 1, images_N/ is N."""
    folders = {}
    for path in data_dir.iterdir():
        match = re.fullmatch(r"images(?:_(\d+))?", path.name)
        if match and path.is_dir():
            folders[int(match.group(1) or 1)] = path
    return folders


def llff_image_files(folder: Path) -> list[Path]:
    """The folder's .jpg/.jpeg/.png images (any case) in nerf-pytorch's order: sorted names."""
    return sorted(path for path in folder.iterdir() if path.suffix.lower() in LLFF_IMAGE_SUFFIXES)


def choose_factor(folders: dict[int, Path], resolution: int | None, factor: int | None) -> int:
    """`factor` if given; else images_8 without a resolution; else the smallest images at least
    `resolution` wide (least decoding, no upscaling)."""
    available = ", ".join(path.name for _, path in sorted(folders.items())) or "none"
    if factor is not None:
        if factor not in folders:
            raise UserError(f"LLFF folder images_{factor} not found (available: {available})")
        return factor
    if not folders:
        raise UserError("LLFF dataset has no images_N/ folder next to poses_bounds.npy")
    if resolution is None:
        return LLFF_DEFAULT_FACTOR if LLFF_DEFAULT_FACTOR in folders else max(folders)
    wide_enough = [f for f, folder in folders.items() if first_width(folder) >= resolution]
    if not wide_enough:
        raise UserError(f"no LLFF image folder is at least {resolution} px wide (available: {available})")
    return max(wide_enough)


def first_width(folder: Path) -> int:
    files = llff_image_files(folder)
    if not files:
        raise UserError(f"no images in {folder}")
    return image_shape(files[0])[1]


def holdout_splits(n: int) -> dict[str, tuple[int, ...]]:
    """nerf-pytorch's llffhold: test = every 8th view from 0, val = test, train = the rest."""
    test = tuple(range(0, n, LLFF_HOLD))
    return {"train": tuple(i for i in range(n) if i % LLFF_HOLD), "val": test, "test": test}


def load_llff(data_dir: Path, resolution: int | None, with_images: bool,
              background: tuple[float, float, float], factor: int | None) -> Dataset:
    """LLFF as nerf-pytorch loads it, in NDC: focal = hwf focal / factor at the images_{factor} size
    (then scaled with any further area downscale to `resolution`); alpha, if any, is dropped."""
    poses, bounds = read_poses_bounds(data_dir / "poses_bounds.npy")
    folders = llff_folders(data_dir)
    factor = choose_factor(folders, resolution, factor)
    paths = llff_image_files(folders[factor])
    if len(paths) != len(poses):
        raise UserError(f"{folders[factor]} holds {len(paths)} images but poses_bounds.npy has {len(poses)} poses")
    height, width = common_shape(paths, (3, 4))
    focal = float(np.float32(poses[0, 2, 4] * (1.0 / factor)))  # the first view's hwf serves all, as there
    size = scaled_size(width, height, resolution)
    cameras = tuple(pinhole(c2w, width, height, focal).resized(*size) for c2w in llff_c2w(poses, bounds))
    first = cameras[0]
    ndc = NDCSpace(first.width / (2.0 * first.fx), first.height / (2.0 * first.fx), 1.0)
    images = load_images(paths, size, background, composite=False)[0] if with_images else None
    return Dataset("llff", images, cameras, holdout_splits(len(poses)), 0.0, 1.0, ndc, background, LLFF_AABB)


# ---- captures: Instant-NGP's and nerfstudio's transforms.json (read by train.scene.captures) --------------

def fit_lens(frame: CaptureFrame, stored: tuple[int, int]) -> Camera:
    """A frame's camera at its image as stored (`stored`: width, height, which w and h must say where given), with
    its lens (runtime.lens: OpenCV's; the fit takes no fisheye and no k4)."""
    camera = frame.camera(stored)
    if (camera.width, camera.height) != stored:
        raise UserError(f"{frame.where}: w and h say {camera.width}x{camera.height}, but {frame.path} is "
                        f"{stored[0]}x{stored[1]}")
    if frame.model == FISHEYE_MODEL:
        raise UserError(f"{frame.where}: a fisheye capture is not fitted (its lens bends rays the fit's does not); "
                        "`noisenerf import-nerfstudio` imports a nerfstudio run of it")
    if frame.coefficients(("k4",))[0]:
        raise UserError(f"{frame.where}: k4 is not supported (an r^8 term the fit's lens lacks: k1, k2, k3, p1, p2)")
    return dataclasses.replace(camera, lens=frame.lens())


def capture_camera(stated: Camera, c2w: np.ndarray, size: tuple[int, int]) -> Camera:
    """`stated`'s intrinsics at `size` (width, height) and pose c2w (4, 4): x scales by the width ratio and y by
    the height ratio, as the area downscale maps them (they differ by the height's rounding). The lens acts on
    normalised coordinates, so it does not scale."""
    sx, sy = size[0] / stated.width, size[1] / stated.height
    return Camera(matrix_rows(c2w), *size, stated.fx * sx, stated.fy * sy, stated.cx * sx, stated.cy * sy, stated.lens)


def rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """The shortest rotation taking unit vector `up` onto +z (Rodrigues); a half turn about x for −z, where the
    shortest one is not unique. (3,) -> (3, 3)."""
    if up[2] < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    ax, ay, _ = np.cross(up, [0.0, 0.0, 1.0])
    cross = np.array([[0.0, 0.0, ay], [0.0, 0.0, -ax], [-ay, ax, 0.0]])
    return np.eye(3) + cross + cross @ cross / (1.0 + up[2])


def normalized_poses(c2w: np.ndarray, path: Path) -> np.ndarray:
    """nerfstudio's default dataparser normalisation (auto_orient_and_center_poses with method "up" and
    center_method "poses", then auto_scale_poses), in float64:
    1. rotate the world by the shortest rotation taking the mean camera up vector (c2w's y column) to +z;
    2. move the mean camera position to the origin;
    3. scale the positions by one factor so that the largest absolute camera coordinate is 1.
    (n, 4, 4) -> (n, 4, 4)."""
    up = c2w[:, :3, 1].mean(axis=0)
    if not np.linalg.norm(up) > 1e-9:
        raise UserError(f"{path}: the cameras' up vectors cancel out: there is no up to orient the scene by")
    rotation = rotation_onto_z(up / np.linalg.norm(up))
    positions = (c2w[:, :3, 3] - c2w[:, :3, 3].mean(axis=0)) @ rotation.T
    extent = np.abs(positions).max()
    if not extent > 1e-9 * (1.0 + np.abs(c2w[:, :3, 3]).max()):
        raise UserError(f"{path}: all cameras stand at one point; a NeRF needs views from different places")
    normalized = np.tile(np.eye(4), (len(c2w), 1, 1))
    normalized[:, :3, :3] = rotation @ c2w[:, :3, :3]
    normalized[:, :3, 3] = positions / extent
    return normalized


def farthest_corner(positions: np.ndarray, aabb: tuple[float, ...]) -> float:
    """The largest distance from a camera to a corner of the box, so a ray sampled out to it crosses the whole
    box. positions: (n, 3)."""
    corners = np.array(list(itertools.product(*zip(aabb[:3], aabb[3:]))))
    return float(np.linalg.norm(positions[:, None] - corners[None], axis=-1).max())


def load_capture(data_dir: Path, resolution: int | None, with_images: bool,
                 background: tuple[float, float, float]) -> Dataset:
    """One transforms.json, as Instant-NGP's colmap2nerf.py and nerfstudio's ns-process-data write it, read and
    checked by `read_capture` (train.scene.captures: what is accepted).

    Frames whose image file is missing are left out (`Dataset.skipped`), as Instant-NGP does for a file that
    states sharpness (colmap2nerf.py's) and nerfstudio's instant-ngp dataparser does for any: colmap2nerf.py's
    capture of Instant-NGP's fox lists 67 frames beside 50 images. The others (file_path relative to the folder)
    are sorted by image file, then every 8th from the first is held out as test (and val), LLFF's convention
    (`holdout_splits`): a capture has no test split of its own.
    Intrinsics are each frame's (`fit_lens`), scaled with the image to `resolution` (`capture_camera`).
    Poses are normalised as nerfstudio's dataparser does (`normalized_poses`), so the cameras span [-1, 1]^3;
    the box is [-aabb_scale, aabb_scale]^3: Instant-NGP's aabb_scale (default 1) extends it beyond the cameras
    for the content around them. Rays run from near 0.05 to the farthest box corner seen from any camera: with
    the near plane close to the cameras, every ray's samples cover all of the box in front of it. RGBA images are
    composited on `background` as NeRF-Synthetic's are; their alpha is kept for space carving only without
    distortion, since carving projects through the pinhole cameras. nerfstudio's applied_transform and
    applied_scale change nothing here: the normalisation orients, centres and scales the poses as saved.
    """
    capture = read_capture(data_dir)
    present = [frame.path.is_file() for frame in capture.frames]
    frames = sorted((f for f, found in zip(capture.frames, present) if found), key=lambda frame: str(frame.path))
    skipped = tuple(sorted(f.file_path for f, found in zip(capture.frames, present) if not found))
    if len(frames) < 2:
        missing = f" ({len(skipped)} of {len(capture.frames)} images missing, the first {skipped[0]})" if skipped else ""
        raise UserError(f"{capture.path}: needs at least two frames with images (one is held out for testing), "
                        f"got {len(frames)}{missing}")
    paths = [frame.path for frame in frames]
    height, width = common_shape(paths, (3, 4))
    stated = [fit_lens(frame, (width, height)) for frame in frames]
    c2w = normalized_poses(np.stack([frame.c2w for frame in frames]), capture.path)
    size = scaled_size(width, height, resolution)
    cameras = tuple(capture_camera(camera, matrix, size) for camera, matrix in zip(stated, c2w))
    distorted = any(camera.lens is not None for camera in cameras)
    aabb = (-capture.aabb_scale,) * 3 + (capture.aabb_scale,) * 3
    images, alphas = load_images(paths, size, background, composite=True) if with_images else (None, None)
    return Dataset("capture", images, cameras, holdout_splits(len(frames)), CAPTURE_NEAR,
                   farthest_corner(c2w[:, :3, 3], aabb), None, background, aabb, None if distorted else alphas,
                   skipped)
