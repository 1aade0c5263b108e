"""The recipient's side: numpy + onnxruntime + OpenImageIO + safetensors, never torch.

Owns the conventions both sides share (cameras, rays, sampling, positional encoding, compositing),
image I/O, the secret bundle format, the onnxruntime session and reveal.
"""
