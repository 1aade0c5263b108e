"""Camera lenses: the distortion nerfstudio's cameras (and COLMAP's OPENCV, Instant-NGP's transforms.json) carry, and
the rays a photo's pixels saw through it.

nerfstudio's model (camera_utils.radial_and_tangential_undistort, cameras.Cameras._generate_rays_from_coords): a
pixel at (u, v) (centre at +pixel_center) has normalised coordinates x_d = (u − cx) / fx, y_d = (v − cy) / fy
(y down), which the lens formed from the undistorted (x, y):

    r² = x² + y²,  d = 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸
    x_d = x d + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y d + 2 p2 x y + p1 (r² + 2 y²)

inverted by 10 Newton steps from (x_d, y_d), a step taken only where the Jacobian's determinant exceeds 1e-3 in
magnitude (nerfstudio's; in float64 here, in both languages). y is flipped to OpenGL's up; an `opencv`
(perspective) lens looks along (x, y, −1), a `fisheye` one (nerfstudio's OPENCV_FISHEYE: the same
polynomial, p1 = p2 = 0, then an equidistant projection) along (x sin θ/θ, y sin θ/θ, −cos θ), θ = |(x, y)| clipped
to [0, π]. A lens whose inversion does not land back on its pixels (the polynomial folds over inside the image) is
refused. web/src/camera.js mirrors this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import checked_float

LENS_MODELS = ("opencv", "fisheye")
COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2")  # nerfstudio's distortion_params, in its order
MAX_COEFFICIENT = 1e3  # real lenses stay within ±10; a file stating more is refused
NEWTON_STEPS = 10  # nerfstudio's max_iterations
SINGULAR = 1e-3  # nerfstudio's eps: no step where |det J| is at most this
TOLERANCE_PX = 1e-3  # an inversion further than this from its pixel has not converged (the model folds over)


@dataclass(frozen=True)
class Lens:
    """A camera's distortion: its model and nerfstudio's six coefficients."""

    model: str  # opencv | fisheye
    coefficients: tuple[float, ...]  # k1, k2, k3, k4, p1, p2

    def to_dict(self) -> dict:
        return {"model": self.model, **dict(zip(COEFFICIENTS, self.coefficients))}

    @staticmethod
    def from_dict(data) -> "Lens":
        """From metadata someone else wrote: a known model, the six coefficients finite within ±MAX_COEFFICIENT
        (a fisheye's p1 and p2 zero), nothing else."""
        if not isinstance(data, dict) or set(data) != {"model", *COEFFICIENTS} or data["model"] not in LENS_MODELS:
            raise UserError(f"a camera's lens must be an object with a model ({' or '.join(LENS_MODELS)}) and "
                            f"{', '.join(COEFFICIENTS)}", code="camera.lens", models=list(LENS_MODELS))
        coefficients = tuple(checked_float(data[key], f"lens {key}", -MAX_COEFFICIENT, MAX_COEFFICIENT,
                                           code="camera.lens_coefficient", key=key) for key in COEFFICIENTS)
        if data["model"] == "fisheye" and any(coefficients[4:]):
            raise UserError("a fisheye lens has no tangential coefficients (p1, p2 must be 0)",
                            code="camera.lens_coefficient", key="p1" if coefficients[4] else "p2")
        return Lens(data["model"], coefficients)


def distort(x: np.ndarray, y: np.ndarray, coefficients) -> tuple[np.ndarray, np.ndarray]:
    """The lens's forward model (module docstring), float64. (n,), (n,) -> x_d, y_d: (n,)."""
    k1, k2, k3, k4, p1, p2 = coefficients
    r = x * x + y * y
    d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)))
    return d * x + 2 * p1 * x * y + p2 * (r + 2 * x * x), d * y + 2 * p2 * x * y + p1 * (r + 2 * y * y)


def undistort(x_d: np.ndarray, y_d: np.ndarray, coefficients) -> tuple[np.ndarray, np.ndarray]:
    """nerfstudio's inversion of `distort` (module docstring), float64. (n,), (n,) -> x, y: (n,)."""
    k1, k2, k3, k4, p1, p2 = coefficients
    x, y = np.array(x_d, np.float64), np.array(y_d, np.float64)
    with np.errstate(all="ignore"):
        for _ in range(NEWTON_STEPS):
            r = x * x + y * y
            d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)))
            fx = d * x + 2 * p1 * x * y + p2 * (r + 2 * x * x) - x_d
            fy = d * y + 2 * p2 * x * y + p1 * (r + 2 * y * y) - y_d
            d_r = k1 + r * (2.0 * k2 + r * (3.0 * k3 + r * 4.0 * k4))
            d_x, d_y = 2.0 * x * d_r, 2.0 * y * d_r
            fx_x = d + d_x * x + 2.0 * p1 * y + 6.0 * p2 * x
            fx_y = d_y * x + 2.0 * p1 * x + 2.0 * p2 * y
            fy_x = d_x * y + 2.0 * p2 * y + 2.0 * p1 * x
            fy_y = d + d_y * y + 2.0 * p2 * x + 6.0 * p1 * y
            denominator = fy_x * fx_y - fx_x * fy_y
            taken = np.abs(denominator) > SINGULAR
            x = x + np.where(taken, (fx * fy_y - fy * fx_y) / denominator, 0.0)
            y = y + np.where(taken, (fy * fx_x - fx * fy_x) / denominator, 0.0)
    return x, y


def border_positions(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixel centres along an image's four edges, where a lens's polynomial folds over first. -> px, py (n,)."""
    across, down = np.arange(width) + 0.5, np.arange(height) + 0.5
    px = np.concatenate([across, across, np.full(height, 0.5), np.full(height, width - 0.5)])
    py = np.concatenate([np.full(width, 0.5), np.full(width, height - 0.5), down, down])
    return px, py


def lens_directions(lens: Lens, fx: float, fy: float, cx: float, cy: float, px: np.ndarray, py: np.ndarray,
                    width: int, height: int) -> np.ndarray:
    """Camera-space directions (n, 3) float64 of image positions (px, py) in pixels seen through `lens`
    (module docstring), refusing a lens that folds over inside the width × height image."""
    x_d, y_d = (np.asarray(px, np.float64) - cx) / fx, (np.asarray(py, np.float64) - cy) / fy
    x, y = undistort(x_d, y_d, lens.coefficients)
    back_x, back_y = distort(x, y, lens.coefficients)
    with np.errstate(invalid="ignore"):
        miss = np.maximum(np.abs(back_x - x_d) * fx, np.abs(back_y - y_d) * fy)
    if not np.all(miss <= TOLERANCE_PX):  # NaN too
        raise UserError(f"a {lens.model} lens {lens.coefficients} cannot be undone across a {width}x{height} image: "
                        "its distortion folds over inside it", code="camera.lens_folds", model=lens.model)
    y = -y  # OpenCV's y down to OpenGL's up
    if lens.model == "opencv":
        return np.stack([x, y, -np.ones_like(x)], axis=-1)
    theta = np.clip(np.sqrt(x * x + y * y), 0.0, np.pi)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(theta > 0, np.sin(theta) / theta, 1.0)
    return np.stack([x * scale, y * scale, -np.cos(theta)], axis=-1)
