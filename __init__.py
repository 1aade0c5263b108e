"""noisenerf: hide secret images in a frozen NeRF (Noise-NeRF), reveal them with onnxruntime.

The library, beside the command lines (README, "Python API"):

    import noisenerf
    result = noisenerf.reveal("model.onnx", "secret.bundle")      # the base install: no torch
    view = noisenerf.render("model.onnx", view=3)
    noisenerf.hide("scene/", secret, "secret.bundle")   # the train extra: fit, import_nerfstudio, import_ingp, hide, export_model

Names resolve on first use, so `import noisenerf` loads nothing heavy (onnxruntime, torch) by itself.
"""

__version__ = "0.1.0"

# public name -> the module that owns it
API = {**{name: "noisenerf.runtime.api" for name in ("reveal", "render", "RevealResult", "RenderResult")},
       **{name: "noisenerf.api" for name in ("fit", "import_nerfstudio", "import_ingp", "hide", "export_model")},
       **{name: "noisenerf.runtime.errors" for name in ("UserError", "InexactResult")},
       "ProgressEvent": "noisenerf.runtime.progress"}
__all__ = ["__version__", *API]


def __getattr__(name: str):
    if name not in API:
        raise AttributeError(f"module 'noisenerf' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(API[name]), name)
