"""Cameras and rays, shared by training, hiding and reveal.

Convention: NeRF-Synthetic / OpenGL camera-to-world matrices (the camera looks down −z, +y is up).
Ray directions are not normalised: their camera-space z is −1 (a pinhole's, or through an OpenCV lens:
runtime.lens), so a ray parameter t is depth along the optical axis, as in nerf-pytorch (a fisheye's are unit
vectors, as nerfstudio's); `viewdirs` are the normalised directions the field is conditioned on.
Pixel (i, j) is shot through (i + pixel_center, j + pixel_center): 0.5 hits pixel centres (our scenes),
0.0 reproduces nerf-pytorch renders of imported checkpoints.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.lens import Lens, border_positions, lens_directions
from noisenerf.runtime.limits import checked_float, checked_image_size


@dataclass(frozen=True)
class Camera:
    """A camera: 4×4 camera-to-world (row-major, nested tuples), image size and intrinsics, and its lens's
    distortion (runtime.lens) where it has one (None: a pinhole)."""

    c2w: tuple[tuple[float, ...], ...]
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    lens: Lens | None = None

    @staticmethod
    def from_fov(c2w: np.ndarray, width: int, height: int, fov_x: float) -> "Camera":
        """Square pixels, principal point at the image centre, horizontal field of view in radians."""
        focal = 0.5 * width / np.tan(0.5 * fov_x)
        return Camera(_as_tuple(c2w), int(width), int(height), float(focal), float(focal), 0.5 * width, 0.5 * height)

    def resized(self, width: int, height: int) -> "Camera":
        """The same view at another resolution: horizontal field of view kept, square pixels."""
        scale = width / self.width
        return dataclasses.replace(
            self, width=int(width), height=int(height), fx=self.fx * scale, fy=self.fx * scale,
            cx=0.5 * width, cy=0.5 * height,
        )

    def matrix(self) -> np.ndarray:
        """The camera-to-world matrix as a (4, 4) float32 array."""
        return np.asarray(self.c2w, dtype=np.float32).reshape(4, 4)

    def to_dict(self) -> dict:
        """As metadata states it; a pinhole's has no lens key (what every camera before lenses wrote)."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "lens"}
        return {**fields, **({"lens": self.lens.to_dict()} if self.lens is not None else {})}

    @staticmethod
    def from_dict(data) -> "Camera":
        """From metadata someone else wrote: integer size within the caps, finite intrinsics, finite pose."""
        if not isinstance(data, dict):
            raise UserError("malformed camera: expected an object", code="camera.not_object")
        try:
            c2w = np.asarray(data["c2w"])
            if c2w.shape == (3, 4):
                c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
            if c2w.shape != (4, 4) or c2w.dtype.kind not in "iuf" or not np.isfinite(c2w).all():
                raise ValueError("c2w must be a finite 4x4 matrix")
            width, height = checked_image_size(data["width"], data["height"], "camera", code="camera.size")
            fx, fy = (checked_float(data[name], f"camera {name}", 1e-6, 1e9, code="camera.focal", key=name)
                      for name in ("fx", "fy"))
            cx, cy = (checked_float(data[name], f"camera {name}", -1e9, 1e9, code="camera.center", key=name)
                      for name in ("cx", "cy"))
        except KeyError as error:
            raise UserError(f"malformed camera: {error}", code="camera.missing_key", key=error.args[0]) from None
        except (TypeError, ValueError) as error:  # numpy's words, or ours
            raise UserError(f"malformed camera: {error}", code="camera.bad_c2w") from None
        camera = Camera(_as_tuple(c2w), width, height, fx, fy, cx, cy,
                        None if data.get("lens") is None else Lens.from_dict(data["lens"]))
        if camera.lens is not None:  # a lens that folds over inside the image is refused when read, not mid-render
            lens_directions(camera.lens, fx, fy, cx, cy, *border_positions(width, height), width, height)
        return camera


@dataclass(frozen=True)
class NDCSpace:
    """nerf-pytorch's normalised device coordinates for forward-facing (LLFF) scenes.

    The space is a property of the scene (the training camera's field of view), not of the camera a view
    is rendered with, so a secret at any resolution lands in the same space the field was fitted in.
    """

    tan_half_fov_x: float
    tan_half_fov_y: float
    near_plane: float = 1.0

    @staticmethod
    def from_dict(data) -> "NDCSpace":
        """From metadata: positive finite values only (a zero would divide by zero in every ray)."""
        if not isinstance(data, dict) or not {"tan_half_fov_x", "tan_half_fov_y"} <= set(data) <= {
                "tan_half_fov_x", "tan_half_fov_y", "near_plane"}:
            raise UserError("ndc must be an object with tan_half_fov_x, tan_half_fov_y and near_plane",
                            code="camera.bad_ndc")
        return NDCSpace(**{name: checked_float(value, f"ndc {name}", 1e-6, 1e6, code="camera.ndc_value", key=name)
                           for name, value in data.items()})


def _as_tuple(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(matrix, dtype=np.float64).reshape(4, 4))


def camera_rays(camera: Camera, pixel_center: float, rect: tuple[int, int, int, int] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays of a camera's pixels, row-major.

    rect: optional (x0, y0, width, height) sub-rectangle of the image.
    Returns rays_o, rays_d: (n_rays, 3) float32, rays_d with camera-space z = −1.
    """
    x0, y0, width, height = rect if rect is not None else (0, 0, camera.width, camera.height)
    i, j = np.meshgrid(np.arange(x0, x0 + width, dtype=np.float32), np.arange(y0, y0 + height, dtype=np.float32),
                       indexing="xy")
    return pixel_rays(camera, i.ravel() + pixel_center, j.ravel() + pixel_center)


def pixel_rays(camera: Camera, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through image-plane positions (px, py) in pixels, through the camera's lens where it has one.
    px, py: (n,) -> rays_o, rays_d: (n, 3)."""
    c2w = camera.matrix()
    if camera.lens is not None:
        dirs = lens_directions(camera.lens, camera.fx, camera.fy, camera.cx, camera.cy, px, py, camera.width,
                               camera.height)
    else:
        dirs = np.stack([(px - camera.cx) / camera.fx, -(py - camera.cy) / camera.fy, -np.ones_like(px)], axis=-1)
    rays_d = (dirs.astype(np.float32) @ c2w[:3, :3].T).astype(np.float32)
    rays_o = np.broadcast_to(c2w[:3, 3], rays_d.shape).astype(np.float32)
    return rays_o, rays_d


def normalize_directions(rays_d: np.ndarray) -> np.ndarray:
    """Unit view directions. rays_d: (n, 3) -> (n, 3); a zero-length direction is refused."""
    norms = np.linalg.norm(rays_d, axis=-1, keepdims=True)
    if not np.all(norms > 0):
        raise UserError("a ray has a zero-length direction", code="camera.zero_direction")
    return (rays_d / norms).astype(np.float32)


def ndc_rays(space: NDCSpace, rays_o: np.ndarray, rays_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """nerf-pytorch's ndc_rays: shift origins to the near plane, then project. (n, 3) -> (n, 3), (n, 3)."""
    t = -(space.near_plane + rays_o[:, 2]) / rays_d[:, 2]
    rays_o = rays_o + t[:, None] * rays_d
    ox, oy, oz = rays_o[:, 0], rays_o[:, 1], rays_o[:, 2]
    dx, dy, dz = rays_d[:, 0], rays_d[:, 1], rays_d[:, 2]
    ax, ay = -1.0 / space.tan_half_fov_x, -1.0 / space.tan_half_fov_y
    ndc_o = np.stack([ax * ox / oz, ay * oy / oz, 1.0 + 2.0 * space.near_plane / oz], axis=-1)
    ndc_d = np.stack([ax * (dx / dz - ox / oz), ay * (dy / dz - oy / oz), -2.0 * space.near_plane / oz], axis=-1)
    return ndc_o.astype(np.float32), ndc_d.astype(np.float32)
