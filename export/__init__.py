"""The sender's export (torch + onnx): a scene's frozen field -> one self-contained ONNX model file."""
