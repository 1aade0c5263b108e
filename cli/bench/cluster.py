"""Hiding on Ray: the same multi-tile secret hidden by the local executor and by Ray at 1 and 2 workers
(Ray's overhead as a ratio to local, and whether the bundles are byte-identical), and a phone photo's
12 megapixels hidden end to end through Ray and revealed.

The bench starts each Ray cluster itself (ray.init with that many CPUs, a small object store, no
dashboard) and times the hide alone; the cluster's start is reported apart. Ray binds the machine's
network address: run the bench inside a loopback-only network namespace (`unshare -n`) where that
address must not listen.
"""

from __future__ import annotations

import contextlib
import importlib.util
import tempfile
import time

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, peak_rss_gib, resized, timed
from noisenerf.cli.bench.report import verdict

RAY_OVERHEAD_GOAL = 1.5  # Ray's hide time ÷ the local executor's, same workers, same secret
OBJECT_STORE_BYTES = 256 * 2 ** 20


@contextlib.contextmanager
def ray_cluster(cpus: int):
    """A local Ray cluster of `cpus` worker CPUs for the block; yields the seconds it took to start."""
    import ray

    started = time.perf_counter()
    ray.init(num_cpus=cpus, object_store_memory=OBJECT_STORE_BYTES, include_dashboard=False,
             log_to_driver=False, _temp_dir=tempfile.mkdtemp(prefix="noisenerf-ray-"))
    try:
        yield time.perf_counter() - started
    finally:
        ray.shutdown()


def measure_cluster(context: BenchContext) -> Measured:
    """The multi-tile secret by every executor, then the phone photo through Ray with every CPU."""
    config = context.config
    if importlib.util.find_spec("ray") is None:
        return Measured([{"run": "not measured", "reason": "Ray is not installed (pip install '.[cluster]')"}])
    secret = resized(context.secret, config.cluster_size, config.cluster_size)
    hide_config = HideConfig(view=config.view, tile_size=config.cluster_tile)
    rows = []
    for workers in config.threads:  # each worker count by both executors, local first
        local = context.hide(secret, f"cluster_local{workers}", hide_config, workers=workers)
        with ray_cluster(workers) as start_seconds:
            report = context.hide(secret, f"cluster_ray{workers}", hide_config, executor="ray")
        reference = (context.work / f"cluster_local{config.threads[0]}.bundle").read_bytes()
        for run, hidden in (("local", local), ("ray", report)):
            rows.append({"run": f"{run}, {workers} workers", "pixels": secret[..., 0].size,
                         "tiles": len(hidden["tiles"]), "hide_seconds": hidden["seconds"],
                         "cluster_start_seconds": start_seconds if run == "ray" else None,
                         "identical": (context.work / f"cluster_{run}{workers}.bundle").read_bytes() == reference,
                         "exact": hidden["exact"], "over_local": hidden["seconds"] / local["seconds"]})
    photo = resized(context.secret, *config.cluster_photo)
    with ray_cluster(max(config.threads)):
        report = context.hide(photo, "cluster_photo", HideConfig(view=config.view), executor="ray")
    revealed, reveal_seconds = timed(reveal_tiles, load_bundle(context.work / "cluster_photo.bundle", context.model.mask_secret),
                                     context.model.render_config, context.model.fields())
    rows.append({"run": f"photo through ray, {max(config.threads)} workers", "pixels": photo[..., 0].size,
                 "tiles": len(report["tiles"]), "hide_seconds": report["seconds"], "exact": revealed.exact,
                 "reveal_seconds": reveal_seconds, "bytes_per_pixel": report["bytes_per_pixel"],
                 "driver_peak_rss_gib": peak_rss_gib()})
    return Measured(rows)


def optional(value: float | None, spec: str) -> str:
    return "—" if value is None else format(value, spec)


def describe_cluster(context: BenchContext, measured: Measured) -> list[str]:
    rows, config = measured.rows, context.config
    if rows[0]["run"] == "not measured":
        return [f"Not measured: {rows[0]['reason']}."]
    worst = max(row["over_local"] for row in rows if row["run"].startswith("ray,"))
    photo = rows[-1]
    lines = [f"`{config.secret}` resized to {config.cluster_size}² in {config.cluster_tile}-px tiles, hidden by "
             f"the local executor and by a local Ray cluster started by the bench (its start not counted); "
             f"then resized to {config.cluster_photo[0]}×{config.cluster_photo[1]} (a phone camera's 12 MP) and "
             "hidden end to end through Ray.", "",
             f"- Ray ÷ local hide time at the same number of workers: worst **{worst:.2f}×** (goal ≤ {RAY_OVERHEAD_GOAL}: "
             f"{verdict(worst, RAY_OVERHEAD_GOAL, lower_is_better=True)}); bundles byte-identical to local: "
             f"**{str(all(row.get('identical', True) for row in rows)).lower()}**.",
             f"- 12 MP through Ray: hide {photo['hide_seconds'] / 60:.1f} min, {photo['tiles']} tiles, "
             f"{photo['bytes_per_pixel']:.2f} bytes per pixel, reveal {photo['reveal_seconds']:.1f} s, exact "
             f"{str(photo['exact']).lower()}; the bench process's peak RSS {photo['driver_peak_rss_gib']:.2f} GiB.",
             "", "| run | pixels | tiles | hide s | cluster start s | ÷ local | byte-identical | exact |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['run']} | {r['pixels']:,} | {r['tiles']} | {r['hide_seconds']:.1f} | "
              f"{optional(r.get('cluster_start_seconds'), '.1f')} | {optional(r.get('over_local'), '.2f')} | "
              f"{str(r.get('identical', '—')).lower()} | {str(r['exact']).lower()} |" for r in rows]
    return lines
