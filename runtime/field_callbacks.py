"""The field callbacks of the numpy render pipeline (nerfacc's rgb_sigma_fn) and how a field becomes one.

A backend (onnxruntime's runtime.session.OnnxField, or torch behind train.scene.render.numpy_field) is a
FieldFn, or a NoisyFieldFn when it takes the noise port; the pipeline calls a SampleFieldFn, which also
learns which ray and sample each point is, so that a reveal looks its noise up by those indices.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

# field(points (m, 3), viewdirs (m, 3)) -> rgb (m, 3), sigma (m,)
FieldFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
# field(points (m, 3), viewdirs (m, 3), noise (m, dims)) -> rgb (m, 3), sigma (m,)
NoisyFieldFn = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
# callback(points (m, 3), viewdirs (m, 3), ray index (m,), sample index (m,)) -> rgb (m, 3), sigma (m,)
SampleFieldFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def plain(field: FieldFn) -> SampleFieldFn:
    """An ordinary field as the pipeline's callback."""
    return lambda points, viewdirs, rays, samples: field(points, viewdirs)


def noisy(field: NoisyFieldFn, noise: np.ndarray) -> SampleFieldFn:
    """A field with noise at every sample: noise (n_rays, 1 or n_samples, dims) float32, one vector per ray
    (ray and compact layouts) or per sample (the paper's layout)."""
    per_ray = noise.shape[1] == 1
    return lambda points, viewdirs, rays, samples: field(points, viewdirs, noise[rays, 0 if per_ray else samples])
