"""noisenerf: hide secret images in a frozen NeRF (Noise-NeRF), reveal them with onnxruntime."""

__version__ = "0.1.0"
