"""The `ingp` experiment: an Instant-NGP snapshot imported (`noisenerf import-ingp`), exported, rendered, and the
bench's photos hidden in it at two of its cameras (revealed through onnxruntime and in the page).

No Instant-NGP build runs here, so nothing renders the snapshot as Instant-NGP would: the field's agreement with
Instant-NGP's network is the tests' (tests/test_import_ingp.py, evaluated independently from the snapshot's flat
parameters); this experiment measures the import's cost and that hides in such a scene are exact.

Rows (ingp.csv): "import" (seconds to import, export, render one camera; parameters, file bytes) and "hide" (as
the fields experiment's).
"""

from __future__ import annotations

import time
from pathlib import Path


from noisenerf.runtime.api import render

from noisenerf.cli.bench.context import BenchContext, Measured
from noisenerf.cli.bench.fields import imported_hides, median_of


def measure_ingp(context: BenchContext) -> Measured:
    from noisenerf.export.onnx_export import export_scene
    from noisenerf.runtime.errors import UserError
    from noisenerf.train.scene.import_ingp import import_ingp

    config = context.config
    if not config.ingp_snapshot:
        raise UserError("the ingp experiment imports a snapshot: give --ingp-snapshot")
    folder = context.work / "ingp"
    folder.mkdir(exist_ok=True)
    start = time.perf_counter()
    scene = import_ingp(Path(config.ingp_snapshot), folder / "scene")
    imported = time.perf_counter()
    export_scene(folder / "scene", folder / "model.onnx")
    exported = time.perf_counter()
    view = len(scene.config.cameras) // 2
    image = render(folder / "model.onnx", view).image
    rows = [{"row": "import", "import_seconds": imported - start, "export_seconds": exported - imported,
             "render_seconds": time.perf_counter() - exported, "render_view": view,
             "render_width": image.shape[1], "render_height": image.shape[0],
             "parameters": sum(array.size for array in scene.weight_arrays().values()),
             "snapshot_bytes": Path(config.ingp_snapshot).stat().st_size,
             "model_bytes": (folder / "model.onnx").stat().st_size, "cameras": len(scene.config.cameras)}]
    return Measured(rows + imported_hides(context, folder, "ingp")[1])


def describe_ingp(context: BenchContext, measured: Measured) -> list[str]:
    config, rows = context.config, measured.rows
    imported = next(row for row in rows if row["row"] == "import")
    lines = [f"Snapshot `{config.ingp_snapshot}` ({imported['snapshot_bytes'] / 2 ** 20:.1f} MiB, "
             f"{imported['parameters']:,} parameters, {imported['cameras']} cameras) imported in "
             f"{imported['import_seconds']:.1f} s (the occupancy grid built from the field included) and exported in "
             f"{imported['export_seconds']:.1f} s ({imported['model_bytes'] / 2 ** 20:.1f} MiB); camera "
             f"{imported['render_view']} ({imported['render_width']}×{imported['render_height']}) rendered in "
             f"{imported['render_seconds']:.2f} s through onnxruntime.", "",
             "Render agreement with Instant-NGP itself is not measured here (no build of it runs on this machine); the "
             "field equals Instant-NGP's network evaluated independently from the snapshot's parameters "
             "(tests/test_import_ingp.py)."]
    hides = [row for row in rows if row["row"] == "hide"]
    lines += ["", f"Photos ({config.nerfstudio_width} px wide) hidden with the defaults at two of its cameras, "
                  "medians:", "",
              "| bytes/px | hide s | reveal s (onnxruntime) | reveal s (browser) | exact (onnxruntime, browser) |",
              "|---|---|---|---|---|",
              f"| {median_of(rows, 'ingp', 'bytes_per_pixel'):.2f} | {median_of(rows, 'ingp', 'hide_seconds'):.2f} | "
              f"{median_of(rows, 'ingp', 'reveal_seconds'):.3f} | {median_of(rows, 'ingp', 'browser_seconds'):.3f} | "
              f"{sum(row['exact'] for row in hides)}, {sum(row['browser_exact'] is True for row in hides)} / {len(hides)} |"]
    return lines
