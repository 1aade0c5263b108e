"""Write a NeRF-Synthetic scene's training frames as a capture: the one transforms.json that nerfstudio's
ns-process-data writes (PINHOLE, fl_x/fl_y/cx/cy/w/h, OpenGL transform matrices) beside RGB photos composited
on white, no alpha, no splits: what `noisenerf fit` reads from a phone capture, 360° round its subject, for
comparing the field kinds (`fit`, or the fields bench's `--data`) where no phone capture is at hand. It is not a
phone capture (no lens, exposure
or background clutter), and any figure from it must say so.

    python tools/blender_as_capture.py ../shared/data/scenes/blender/lego -o /tmp/lego_capture
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from noisenerf.runtime.images import write_image
from noisenerf.train.scene.datasets import load_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("blender", type=Path, help="a NeRF-Synthetic scene folder")
    parser.add_argument("-o", "--output", type=Path, required=True)
    args = parser.parse_args()
    dataset = load_dataset(args.blender)  # RGBA composited on white, at the stored size
    train = dataset.splits["train"]
    (args.output / "images").mkdir(parents=True, exist_ok=False)
    frames = []
    for position, index in enumerate(train):
        name = f"images/frame_{position + 1:05d}.png"
        write_image(args.output / name, np.round(dataset.images[index] * 255).astype(np.uint8))
        frames.append({"file_path": name, "transform_matrix": [list(row) for row in dataset.cameras[index].c2w]})
    camera = dataset.cameras[train[0]]
    (args.output / "transforms.json").write_text(json.dumps({
        "camera_model": "PINHOLE", "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "w": camera.width, "h": camera.height, "camera_angle_x": 2 * math.atan(camera.width / (2 * camera.fx)),
        "frames": frames}, indent=1))
    print(f"{len(frames)} frames -> {args.output}")


if __name__ == "__main__":
    main()
