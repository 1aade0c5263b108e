"""`--executor ray` on a real local Ray cluster: the bundles are byte for byte the local executor's (the
demo secret, a multi-tile one, one interrupted and resumed, one whose worker was killed mid-job), and
without Ray the executor is one line on how to install it.

The cluster runs in a loopback-only network namespace (`unshare -n`, as root or where user namespaces
are allowed), so a test never binds the machine's address; the tests that need it skip, saying why,
where Ray or unshare is missing. CI needs `pip install '.[cluster]'` and unshare (util-linux).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import logging
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from helpers import assert_refused, run_main
from noisenerf.cli.demo import DEMO_VIEW, SECRET_SIZE, TILE_SIZE
from noisenerf.cli.main import main
from noisenerf.runtime.images import write_image
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import DEMO_SCENE, procedural_secret

HERE = Path(__file__).resolve().parent
CPU = torch.device("cpu")
MULTI_SIZE, MULTI_TILE = 40, 16  # as cluster_scenarios.py


def loopback_only_namespace() -> str | None:
    """Why a cluster cannot start here, or None."""
    if importlib.util.find_spec("ray") is None:
        return "ray is not installed (pip install '.[cluster]')"
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is missing: no loopback-only network namespace for the cluster"
    probe = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True)
    if probe.returncode:
        return f"unshare -n is not permitted here ({probe.stderr.decode().strip()[:80]})"
    return None


@pytest.fixture(scope="module")
def ray_hides(tmp_path_factory) -> Path:
    """cluster_scenarios.py run once in a loopback-only namespace: its bundles and report."""
    reason = loopback_only_namespace()
    if reason:
        pytest.skip(reason)
    out = tmp_path_factory.mktemp("ray")
    command = f"ip link set lo up && exec {sys.executable} {HERE / 'cluster_scenarios.py'} {out}"
    done = subprocess.run(["unshare", "-n", "sh", "-c", command], capture_output=True, text=True, timeout=900,
                          env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    assert done.returncode == 0, done.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def local_hides(demo_scene, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local")
    hide(demo_scene, procedural_secret(*SECRET_SIZE), out / "demo.bundle", HideConfig(tile_size=TILE_SIZE, view=DEMO_VIEW),
         CPU, workers=2)
    hide(demo_scene, procedural_secret(MULTI_SIZE, MULTI_SIZE, seed=1), out / "multi.bundle",
         HideConfig(tile_size=MULTI_TILE, view=DEMO_VIEW), CPU, workers=2)
    return out


@pytest.mark.parametrize("name, local", [("demo", "demo"), ("multi", "multi")])
def test_a_ray_hide_is_byte_identical_to_the_local_one(ray_hides, local_hides, name, local):
    assert (ray_hides / f"{name}.bundle").read_bytes() == (local_hides / f"{local}.bundle").read_bytes()


def test_an_interrupted_ray_hide_resumes_to_the_same_bytes(ray_hides, local_hides):
    report = json.loads((ray_hides / "report.json").read_text())
    assert report["saved_when_interrupted"] == 3
    assert (ray_hides / "resumed.bundle").read_bytes() == (local_hides / "multi.bundle").read_bytes()
    assert not (ray_hides / "resumed.bundle.partial").exists()


def test_a_worker_killed_mid_job_is_rerun_and_the_bytes_are_the_same(ray_hides, local_hides):
    assert json.loads((ray_hides / "report.json").read_text())["killed_workers"] == 1
    assert (ray_hides / "killed.bundle").read_bytes() == (local_hides / "multi.bundle").read_bytes()


def test_without_ray_the_executor_is_one_line_on_how_to_install_it(tmp_path, monkeypatch, capfd):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as where it is not installed
    result = run_main(main, ["hide", str(DEMO_SCENE), str(tmp_path / "s.png"), "-o", str(tmp_path / "s.bundle"),
                             "--executor", "ray"], capfd)
    assert_refused(result, tmp_path / "s.bundle", "--executor ray needs Ray: pip install 'noisenerf[cluster]'")


def test_the_bench_measures_ray_against_local_with_identical_bundles(tmp_path):
    """`noisenerf bench --only cluster` at tiny sizes, in the namespace: every Ray bundle is the local one."""
    reason = loopback_only_namespace()
    if reason:
        pytest.skip(reason)
    write_image(tmp_path / "secret.png", procedural_secret(24, 20, seed=2))
    bench = (f"{sys.executable} -m noisenerf.cli.main bench --scene {DEMO_SCENE} --secret {tmp_path / 'secret.png'} "
             f"--only cluster --cluster-size 32 --cluster-tile 16 --cluster-photo 40x30 -o {tmp_path / 'out'}")
    done = subprocess.run(["unshare", "-n", "sh", "-c", f"ip link set lo up && exec {bench}"], capture_output=True,
                          text=True, timeout=900, env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    assert done.returncode == 0, done.stderr[-3000:]
    with open(tmp_path / "out" / "cluster.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["run"] for row in rows] == ["local, 1 workers", "ray, 1 workers", "local, 2 workers", "ray, 2 workers",
                                            "photo through ray, 2 workers"]
    assert all(row["exact"] == "True" for row in rows)
    assert [row["identical"] for row in rows[:4]] == ["True"] * 4
    assert rows[4]["pixels"] == str(40 * 30)


@pytest.mark.parametrize("flags, level, to_driver", [([], logging.ERROR, False), (["--verbose"], logging.INFO, True)])
def test_rays_own_log_lines_reach_stderr_only_when_verbose(tmp_path, monkeypatch, capfd, flags, level, to_driver):
    """What ray.init is asked for (a stand-in ray module records it, then refuses the connection)."""
    asked = {}

    def init(**options):
        asked.update(options)
        raise ConnectionError("no cluster here")
    monkeypatch.setitem(sys.modules, "ray", types.SimpleNamespace(is_initialized=lambda: False, init=init))
    write_image(tmp_path / "s.png", procedural_secret(8, 8, seed=1))
    result = run_main(main, ["hide", str(DEMO_SCENE), str(tmp_path / "s.png"), "-o", str(tmp_path / "s.bundle"),
                             "--executor", "ray", "--quiet", *flags], capfd)
    assert_refused(result, tmp_path / "s.bundle", "cannot connect to the Ray cluster at RAY_ADDRESS: no cluster here")
    assert (asked["logging_level"], asked["log_to_driver"]) == (level, to_driver)
