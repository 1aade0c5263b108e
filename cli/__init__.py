"""Command lines: `noisenerf` (the sender's tools) and `noisenerf-reveal` (the recipient's, runtime only)."""
