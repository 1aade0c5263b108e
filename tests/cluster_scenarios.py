"""Ray hides for tests/test_cluster.py, run in one process (one cluster start) inside a loopback-only
network namespace: `python cluster_scenarios.py OUT` writes OUT/*.bundle and OUT/report.json.

A small local cluster (2 CPUs, an 80 MB object store, no dashboard, its files under OUT) hides the demo
secret, a multi-tile secret, the same interrupted after 3 saved parts and resumed, and the same again
while one worker is killed in the middle of a job (Ray reruns it).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import ray
import torch

from helpers import interrupted_after_saves  # run as a script, this file's folder is sys.path[0]
from noisenerf.cli.demo import DEMO_VIEW, SECRET_SIZE, TILE_SIZE
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import DEMO_SCENE, procedural_secret
from noisenerf.train.scene.scene import load_scene

CPU = torch.device("cpu")
MULTI_SIZE, MULTI_TILE = 40, 16  # a 3 × 3 tiled secret
JOB_TITLE = b"ray::run_job"  # a Ray worker's process title while it runs a job


def descendants() -> list[int]:
    """This process's descendants (the cluster it started: raylet, workers), by pid."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = [], [os.getpid()]
    while frontier:
        children = [pid for pid, parent in parents.items() if parent in frontier]
        found += children
        frontier = children
    return found


def kill_one_running_job(killed: list[int], stop: threading.Event) -> None:
    """SIGKILL the first of our Ray workers seen running a job (once)."""
    while not stop.is_set() and not killed:
        for pid in descendants():
            try:
                title = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if title.startswith(JOB_TITLE):
                time.sleep(0.05)  # inside the job, not at its start
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
        time.sleep(0.01)


def main(out: Path) -> None:
    ray.init(num_cpus=2, object_store_memory=80 * 10 ** 6, include_dashboard=False, log_to_driver=False,
             _temp_dir=str(out / "ray"))
    scene = load_scene(DEMO_SCENE)
    multi = procedural_secret(MULTI_SIZE, MULTI_SIZE, seed=1)
    multi_config = HideConfig(tile_size=MULTI_TILE, view=DEMO_VIEW)
    report = {}

    def timed(name: str, secret, config) -> None:
        started = time.perf_counter()
        hide(scene, secret, out / f"{name}.bundle", config, CPU, executor="ray")
        report[f"{name}_seconds"] = round(time.perf_counter() - started, 2)

    timed("demo", procedural_secret(*SECRET_SIZE), HideConfig(tile_size=TILE_SIZE, view=DEMO_VIEW))
    timed("multi", multi, multi_config)
    try:
        with interrupted_after_saves(3):
            timed("resumed", multi, multi_config)
    except KeyboardInterrupt:
        report["saved_when_interrupted"] = len(list((out / "resumed.bundle.partial").glob("*.safetensors")))
    timed("resumed", multi, multi_config)
    killed, stop = [], threading.Event()
    watcher = threading.Thread(target=kill_one_running_job, args=(killed, stop))
    watcher.start()
    try:
        timed("killed", multi, multi_config)
    finally:
        stop.set()
        watcher.join()
    report["killed_workers"] = len(killed)
    (out / "report.json").write_text(json.dumps(report))
    ray.shutdown()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
