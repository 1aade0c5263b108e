"""Lens distortion of captured photos: OpenCV's radial-tangential model (COLMAP's OPENCV camera), the one
Instant-NGP's and nerfstudio's transforms.json carry as k1, k2, k3, p1, p2.

The model maps undistorted normalised image coordinates (x, y) = ((u − cx) / fx, (v − cy) / fy), y growing
down the rows as in OpenCV, to where the lens forms the point:
    r² = x² + y²,  radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y
A photo's pixel sits at a distorted position, so its ray is found by inverting the model there (Newton's
method in float64, as nerfstudio and COLMAP do) and shooting runtime.camera's pinhole ray through the
undistorted position (which flips y into OpenGL's up). Only training uses these rays: a scene's cameras stay
pinhole, since a rendered view is a pinhole image.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from noisenerf.runtime.camera import Camera, pixel_rays
from noisenerf.runtime.errors import UserError

AT_ORIGIN = tuple(tuple(float(i == j) for j in range(4)) for i in range(4))  # identity c2w: camera space
NEWTON_ITERATIONS = 10  # quadratic convergence: a few suffice for real lenses, the rest are a margin
TOLERANCE_PX = 1e-4  # an inversion further than this from its pixel has not converged (the model folds over)


def distort(x: np.ndarray, y: np.ndarray, coefficients) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's model. x, y: (n,) undistorted normalised coordinates (y down); coefficients: k1, k2, k3, p1, p2.
    -> x_d, y_d: (n,)."""
    k1, k2, k3, p1, p2 = coefficients
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def undistort(x_d: np.ndarray, y_d: np.ndarray, coefficients) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `distort` by Newton's method from (x_d, y_d), float64. (n,), (n,) -> x, y: (n,); where the
    model folds over the result is not an inverse (see `distorted_pixel_rays`)."""
    k1, k2, k3, p1, p2 = coefficients
    x, y = np.asarray(x_d, np.float64), np.asarray(y_d, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(NEWTON_ITERATIONS):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            slope = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))  # d radial / dx = slope · x, likewise y
            ex, ey = (d - target for d, target in zip(distort(x, y, coefficients), (x_d, y_d)))
            # the Jacobian of (x_d, y_d) is symmetric: d x_d / dy = d y_d / dx
            jxx = radial + slope * x * x + 2.0 * p1 * y + 6.0 * p2 * x
            jyy = radial + slope * y * y + 6.0 * p1 * y + 2.0 * p2 * x
            jxy = slope * x * y + 2.0 * p1 * x + 2.0 * p2 * y
            det = jxx * jyy - jxy * jxy
            x, y = x - (ex * jyy - ey * jxy) / det, y - (ey * jxx - ex * jxy) / det
    return x, y


def distorted_pixel_rays(camera: Camera, coefficients, px: np.ndarray, py: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """World rays that a lens with distortion `coefficients` (k1, k2, k3, p1, p2) on `camera`'s pinhole
    intrinsics forms at image positions (px, py) in pixels. (n,), (n,) -> rays_o, rays_d: (n, 3) float32, as
    runtime.camera.pixel_rays (camera-space z = −1). UserError where the model cannot be inverted."""
    x_d = (np.asarray(px, np.float64) - camera.cx) / camera.fx
    y_d = (np.asarray(py, np.float64) - camera.cy) / camera.fy
    x, y = undistort(x_d, y_d, coefficients)
    back_x, back_y = distort(x, y, coefficients)
    miss = np.maximum(np.abs(back_x - x_d) * camera.fx, np.abs(back_y - y_d) * camera.fy)
    if not np.all(miss <= TOLERANCE_PX):  # NaN too
        raise UserError(f"lens distortion {tuple(float(c) for c in coefficients)} cannot be undone across a "
                        f"{camera.width}x{camera.height} image: the model folds over inside it")
    return pixel_rays(camera, camera.cx + camera.fx * x, camera.cy + camera.fy * y)


@functools.lru_cache(maxsize=2)  # one lens per capture as a rule; an entry holds one view's directions
def lens_directions(lens: Camera, coefficients: tuple[float, ...], pixel_center: float) -> np.ndarray:
    """Camera-space directions of every pixel of `lens` (a camera at AT_ORIGIN), row-major; cached, since the
    frames of a capture mostly share one lens and inverting it is the cost. -> (n, 3) float32, read-only."""
    j, i = np.indices((lens.height, lens.width), dtype=np.float64)
    directions = distorted_pixel_rays(lens, coefficients, i.ravel() + pixel_center, j.ravel() + pixel_center)[1]
    directions.setflags(write=False)
    return directions


def distorted_camera_rays(camera: Camera, coefficients, pixel_center: float) -> tuple[np.ndarray, np.ndarray]:
    """`distorted_pixel_rays` of every pixel (i + pixel_center, j + pixel_center), row-major, as
    runtime.camera.camera_rays. -> rays_o, rays_d: (width · height, 3) float32."""
    directions = lens_directions(dataclasses.replace(camera, c2w=AT_ORIGIN), tuple(float(c) for c in coefficients),
                                 float(pixel_center))
    c2w = camera.matrix()
    return np.broadcast_to(c2w[:3, 3], directions.shape).astype(np.float32), directions @ c2w[:3, :3].T
