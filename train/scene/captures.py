"""A capture's transforms.json, read once for the fit (`datasets.load_capture`) and the nerfstudio import
(`import_nerfstudio.dataset_cameras`), as Instant-NGP's scripts/colmap2nerf.py and nerfstudio's ns-process-data
write it.

`read_capture(folder)` parses the file into a frozen `Capture`, every number checked and capped as a camera's
numbers are (runtime.limits), every refusal one line naming the file, the frame (its place in the file) and the
key: the frames in the file's order, each with its image file, pose, camera model, lens coefficients and the
intrinsics it states (`CaptureFrame.camera`: its camera as stated, in pixels of its image), and the keys each tool
writes around the cameras: Instant-NGP's aabb_scale and per-frame sharpness, nerfstudio's applied_transform and
applied_scale. What is specific to one reader stays with it: the fit's images, resolution, pose normalisation and
box; the import's dataparser transform and scale, downscale and frame order.

What is accepted, where nerfstudio's loader (nerfstudio/data/dataparsers/nerfstudio_dataparser.py), Instant-NGP's
(src/nerf_loader.cu) or this project's two readers before this one differed:
- a key a frame states wins over the file's, as in Instant-NGP (the frame's read_lens after the file's) and both
  readers before; nerfstudio reads a frame's key only where the file lacks it, which differs only for a file that
  states a key in both places, which neither tool writes;
- numbers are JSON numbers (nerfstudio's float() and int() would take "12", Instant-NGP's JSON reader does not);
  the sizes w and h are whole numbers, given as integers or as integral floats (colmap2nerf.py writes 1080.0;
  both tools read them), a fraction refused (nerfstudio's int() would drop it);
- the camera model (camera_model, the frame's or the file's: ns-process-data writes it per frame for several
  cameras) is one whose rays runtime.lens reproduces: nerfstudio's perspective models `PINHOLE_MODELS`, or none
  named (Instant-NGP names none), or OPENCV_FISHEYE (Instant-NGP's is_fisheye; the fit refuses it); equirectangular
  and the rest are refused; so is a coefficient not 0 under PINHOLE or SIMPLE_PINHOLE;
- the lens: k1, k2, k3, k4, p1, p2, or nerfstudio's distortion_params list of the six (which stands for the keys
  where given), 0 where not stated (`CaptureFrame.lens`: runtime.lens's; the fit refuses a k4, its lens has none);
- the focal length: fl_x, else camera_angle_x (radians) across w; fl_y, else camera_angle_y, else fl_x
  (Instant-NGP's defaults; nerfstudio's own reader needs fl_x, fl_y, cx and cy); cx, cy default to the image's
  centre and w, h to its size (the import reads no image, so it needs w and h);
- each pose a finite 4×4 (nerfstudio multiplies 4×4 matrices) whose rotation is invertible (the fit refused a
  singular one, the import did not: no view has rays without one); entries within ±`MAX_COORDINATE`;
- aabb_scale in [1, 128] (Instant-NGP's box stops growing at 128; nerfstudio ignores it), default 1;
  applied_transform a finite 3×4 with an invertible rotation; applied_scale in [1e-9, 1e9], default 1;
  sharpness a finite number (Instant-NGP drops blurred frames by it only when told to; nothing here does);
- a frame whose image file is missing is read here like any other; the fit leaves it out (datasets.load_capture),
  as Instant-NGP does in a file that states sharpness and nerfstudio's instant-ngp dataparser in any, and the
  import reads no image;
- the file at most `MAX_CAPTURE_BYTES` (the import's limit before; the fit read any size), 1 to MAX_CAMERAS frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import read_json
from noisenerf.runtime.lens import Lens
from noisenerf.runtime.limits import checked_float, checked_image_size, checked_list, is_finite

CAPTURE_FILE = "transforms.json"
MAX_CAPTURE_BYTES = 64 << 20
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")  # nerfstudio's perspective ones
FISHEYE_MODEL = "OPENCV_FISHEYE"  # nerfstudio's FISHEYE camera type
UNDISTORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
COEFFICIENT_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")  # nerfstudio's distortion_params, in its order
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr")
MAX_AABB_SCALE = 128  # Instant-NGP's largest
MAX_COORDINATE = 1e9  # a pose's entries, as a camera's principal point
FOCAL_RANGE = (1e-6, 1e9)  # px, as runtime.camera's
CENTRE_RANGE = (-1e9, 1e9)  # px, as runtime.camera's
ANGLE_RANGE = (1e-6, math.pi - 1e-6)  # a field of view in radians


@dataclass(frozen=True, eq=False)
class CaptureFrame:
    """One entry of `frames`, every number in it checked; None where the frame and the file leave a key out."""

    file_path: str  # as written, relative to the folder
    path: Path  # the image file: file_path, `.png` added unless it names an image file
    c2w: np.ndarray  # (4, 4) float64 OpenGL camera-to-world as written (both tools write OpenGL's), read-only
    where: str  # how refusals name it: "<transforms.json> frame <index in the file>"
    model: str | None  # one of PINHOLE_MODELS, or None: none named
    width: int | None  # w, h
    height: int | None
    fl_x: float | None
    fl_y: float | None
    camera_angle_x: float | None
    camera_angle_y: float | None
    cx: float | None
    cy: float | None
    distortion: tuple[float, ...]  # COEFFICIENT_KEYS' values, 0 where not stated
    sharpness: float | None

    def coefficients(self, keys) -> tuple[float, ...]:
        """The lens coefficients named by `keys` (of COEFFICIENT_KEYS), in that order."""
        return tuple(self.distortion[COEFFICIENT_KEYS.index(key)] for key in keys)

    def lens(self) -> Lens | None:
        """The frame's lens as nerfstudio bends its rays (runtime.lens): a fisheye's (k1 to k4: nerfstudio's
        dataparser drops p1 and p2 for it), an OpenCV one where any coefficient is not 0, else None (a pinhole). Its
        coefficients are checked as a model's metadata's are."""
        fisheye = self.model == FISHEYE_MODEL
        if not fisheye and not any(self.distortion):
            return None
        coefficients = self.distortion[:4] + (0.0, 0.0) if fisheye else self.distortion
        try:
            return Lens.from_dict({"model": "fisheye" if fisheye else "opencv", **dict(zip(COEFFICIENT_KEYS, coefficients))})
        except UserError as error:
            raise UserError(f"{self.where}: {error}") from None

    def camera(self, image_size: tuple[int, int] | None = None) -> Camera:
        """The frame's pinhole camera as the file states it: its pose as written, its intrinsics in pixels of its
        image as stored: w and h, else `image_size` (width, height: the image's, where the caller has read it);
        fl_x, else from camera_angle_x across the width; fl_y, else from camera_angle_y, else fl_x; cx and cy,
        else the image's centre."""
        size = image_size or (None, None)
        width, height = self.width or size[0], self.height or size[1]
        if width is None or height is None:
            raise UserError(f"{self.where}: needs the image's size, 'w' and 'h'")
        width, height = checked_image_size(width, height, f"{self.where}: image")
        fx = self.fl_x if self.fl_x is not None else focal_of(self.camera_angle_x, width)
        fy = self.fl_y if self.fl_y is not None else (
            fx if self.camera_angle_y is None else focal_of(self.camera_angle_y, height))
        return Camera(tuple(map(tuple, self.c2w.tolist())), width, height, fx, fy,
                      0.5 * width if self.cx is None else self.cx, 0.5 * height if self.cy is None else self.cy)


@dataclass(frozen=True, eq=False)
class Capture:
    """A checked transforms.json."""

    path: Path  # the file
    frames: tuple[CaptureFrame, ...]  # in the file's order
    aabb_scale: float  # Instant-NGP's: the box around the content, in units where the cameras span [-1, 1]
    applied_transform: np.ndarray | None  # (3, 4) float64, nerfstudio's: the poses as saved are it · the originals
    applied_scale: float  # nerfstudio's: the positions as saved are it · the originals


def read_capture(folder) -> Capture:
    """`folder`/transforms.json, checked (the module docstring); UserError naming the file, frame and key."""
    folder = Path(folder)
    path = folder / CAPTURE_FILE
    if path.is_file() and path.stat().st_size > MAX_CAPTURE_BYTES:
        raise UserError(f"{path}: {path.stat().st_size} bytes, more than a {CAPTURE_FILE} ({MAX_CAPTURE_BYTES})")
    meta = read_json(path, CAPTURE_FILE)
    model = camera_model(meta, None, str(path))
    entries = checked_list(meta.get("frames"), f"{path}: 'frames'")
    if not entries:
        raise UserError(f"{path}: 'frames' lists no frames")
    frames = tuple(read_frame(folder, meta, model, entry, f"{path} frame {k}") for k, entry in enumerate(entries))
    applied = meta.get("applied_transform")
    if applied is not None:
        applied = checked_matrix(applied, 3, f"{path}: 'applied_transform'")
        if not abs(np.linalg.det(applied[:, :3])) > 1e-6:
            raise UserError(f"{path}: 'applied_transform' has a rotation that is not invertible")
    return Capture(path, frames,
                   checked_float(meta.get("aabb_scale", 1), f"{path}: 'aabb_scale'", 1.0, MAX_AABB_SCALE), applied,
                   checked_float(meta.get("applied_scale", 1.0), f"{path}: 'applied_scale'", 1e-9, 1e9))


def read_frame(folder: Path, meta: dict, file_model: str | None, entry, where: str) -> CaptureFrame:
    """One entry of `frames`, its own keys over the file's (`meta`)."""
    path, c2w = frame_file_and_pose(folder, entry, where)
    if not abs(np.linalg.det(c2w[:3, :3])) > 1e-6:
        raise UserError(f"{where}: 'transform_matrix' has a rotation that is not invertible")
    c2w.flags.writeable = False

    def value(key):
        return meta.get(key) if entry.get(key) is None else entry[key]

    def number(key, bounds):
        return None if value(key) is None else checked_float(value(key), f"{where}: '{key}'", *bounds)

    model = camera_model(entry, file_model, where)
    width, height = whole(value("w"), f"{where}: 'w'"), whole(value("h"), f"{where}: 'h'")
    checked_image_size(1 if width is None else width, 1 if height is None else height, f"{where}: image")
    if value("fl_x") is None and value("camera_angle_x") is None:
        raise UserError(f"{where}: needs a focal length, 'fl_x' or 'camera_angle_x'")
    distortion = lens_coefficients(value, where)
    if model in UNDISTORTED_MODELS and any(distortion):
        raise UserError(f"{where}: camera_model {model} has no distortion, yet "
                        f"{next(k for k, c in zip(COEFFICIENT_KEYS, distortion) if c)} is not 0")
    frame = CaptureFrame(entry["file_path"], path, c2w, where, model, width, height, number("fl_x", FOCAL_RANGE),
                         number("fl_y", FOCAL_RANGE), number("camera_angle_x", ANGLE_RANGE),
                         number("camera_angle_y", ANGLE_RANGE), number("cx", CENTRE_RANGE), number("cy", CENTRE_RANGE),
                         distortion, None if entry.get("sharpness") is None else
                         checked_float(entry["sharpness"], f"{where}: 'sharpness'"))
    frame.lens()  # its coefficients within a lens's caps
    return frame


def camera_model(entry: dict, inherited: str | None, what: str) -> str | None:
    """The camera model `entry` states (camera_model; OPENCV_FISHEYE for Instant-NGP's is_fisheye), else
    `inherited`; UserError for one whose rays are not a pinhole's bent by OpenCV's polynomial."""
    fisheye = entry.get("is_fisheye")
    if fisheye is not None and not isinstance(fisheye, bool):
        raise UserError(f"{what}: 'is_fisheye' must be true or false, got {fisheye!r:.40}")
    model = "OPENCV_FISHEYE" if fisheye else inherited if entry.get("camera_model") is None else entry["camera_model"]
    if model is not None and model not in (*PINHOLE_MODELS, FISHEYE_MODEL):
        raise UserError(f"{what}: camera_model {model!r:.40} is not supported (expected {', '.join(PINHOLE_MODELS)} "
                        f"or {FISHEYE_MODEL})")
    return model


def lens_coefficients(value, where: str) -> tuple[float, ...]:
    """k1, k2, k3, k4, p1, p2: nerfstudio's distortion_params where given, else each key, 0 where not stated.
    value: key -> the frame's or the file's JSON value."""
    listed = value("distortion_params")
    if listed is not None:
        listed = checked_list(listed, f"{where}: 'distortion_params'", len(COEFFICIENT_KEYS))
        return tuple(checked_float(c, f"{where}: 'distortion_params' {key}")
                     for key, c in zip(COEFFICIENT_KEYS, listed))
    return tuple(0.0 if value(key) is None else checked_float(value(key), f"{where}: '{key}'")
                 for key in COEFFICIENT_KEYS)


def whole(value, what: str):
    """An integral float as the int it is (colmap2nerf.py writes "w": 1080.0); a fraction, NaN or infinity
    refused naming `what`; anything else as it is, for runtime.limits' checks."""
    if isinstance(value, float):
        if not value.is_integer():
            raise UserError(f"{what} must be a whole number, got {value!r:.40}")
        return int(value)
    return value


def focal_of(angle: float, side: int) -> float:
    """The focal length in pixels of a field of view `angle` (radians) across `side` pixels."""
    return 0.5 * side / math.tan(0.5 * angle)


def checked_matrix(value, rows: int, what: str) -> np.ndarray:
    """`rows` JSON rows of 4 numbers, each finite and within ±MAX_COORDINATE. -> (rows, 4) float64."""
    if not (isinstance(value, list) and len(value) == rows
            and all(isinstance(row, list) and len(row) == 4 for row in value)
            and all(not isinstance(v, bool) and isinstance(v, (int, float)) and is_finite(v)
                    and abs(v) <= MAX_COORDINATE for row in value for v in row)):
        raise UserError(f"{what} must be a finite {rows}x4 matrix (numbers within ±{MAX_COORDINATE:g})")
    return np.array(value, dtype=np.float64)


def image_path(folder: Path, file_path: str) -> Path:
    """A frame's file: `file_path` relative to the folder, `.png` added unless it names an image file."""
    path = folder / file_path
    return path if path.suffix.lower() in IMAGE_SUFFIXES else path.with_name(path.name + ".png")


def frame_file_and_pose(folder: Path, frame, where: str) -> tuple[Path, np.ndarray]:
    """One entry of a transforms*.json's `frames` (a capture's or NeRF-Synthetic's): its image file and (4, 4)
    float64 c2w; UserError naming `where` when malformed."""
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise UserError(f"{where}: needs a string 'file_path'")
    if frame.get("transform_matrix") is None:
        raise UserError(f"{where}: needs a numeric 4x4 'transform_matrix'")
    return image_path(folder, frame["file_path"]), checked_matrix(frame["transform_matrix"], 4,
                                                                  f"{where}: 'transform_matrix'")
