"""An 8K secret (7680×4320 by default) hidden and revealed by the two command-line tools, each in a
process of its own, with the memory each used: does it grow with the tile, not with the secret?

Peak memory is the kernel's: a finished process's maximum resident set as wait4 reports it (for the hide,
the largest of the driver and its worker processes), and for the hide's driver alone its high-water mark
(VmHWM) read from /proc while it runs. The hide uses the local executor on every core.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from noisenerf.runtime.images import write_image

from noisenerf.cli.bench.context import BenchContext, Measured, resized

SAMPLE_SECONDS = 0.2  # how often the driver's high-water mark is read


def high_water_mib(pid: int) -> float | None:
    """A running process's peak resident set (VmHWM) in MiB; None once it has gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    line = next((line for line in status.splitlines() if line.startswith("VmHWM:")), None)
    return None if line is None else int(line.split()[1]) / 1024


def run_measured(command: list[str], logs: Path) -> tuple[dict, float, float, float]:
    """Run a noisenerf command with --json -> its report, seconds, the largest process's peak RSS (MiB) and
    its own peak as last sampled (MiB). Its output goes to files in `logs` (the process is reaped by wait4
    alone, which reports its peak). A command that fails stops the bench with its stderr."""
    started = time.perf_counter()
    with open(logs / "stdout", "w+") as stdout, open(logs / "stderr", "w+") as stderr:
        process = subprocess.Popen(command, stdout=stdout, stderr=stderr, text=True)
        sampled, done = [0.0], threading.Event()

        def sample():
            while not done.wait(SAMPLE_SECONDS):
                sampled[0] = max(sampled[0], high_water_mib(process.pid) or 0.0)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        _, status, usage = os.wait4(process.pid, 0)
        done.set()
        sampler.join()
        process.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - started
        if process.returncode != 0:
            stderr.seek(0)
            raise RuntimeError(f"{' '.join(command[2:5])} failed ({process.returncode}): {stderr.read().strip()[-500:]}")
        stdout.seek(0)
        return json.loads(stdout.read()), seconds, usage.ru_maxrss / 1024, sampled[0]


def measure_big_secret(context: BenchContext) -> Measured:
    """The secret resized to config.big_secret, hidden with `noisenerf hide` and revealed with
    `noisenerf-reveal` (onnxruntime), each timed and its memory measured."""
    config = context.config
    photo = resized(context.secret, *config.big_secret)
    write_image(context.work / "big.png", photo)
    bundle, revealed = context.work / "big.bundle", context.work / "big_revealed.png"
    hide, hide_seconds, hide_peak, driver_peak = run_measured(
        [sys.executable, "-m", "noisenerf.cli.main", "hide", config.scene, str(context.work / "big.png"), "-o",
         str(bundle), "--view", str(config.view), "--force", "--json", "--quiet"], context.work)
    reveal, reveal_seconds, reveal_peak, _ = run_measured(
        [sys.executable, "-m", "noisenerf.cli.reveal", str(context.model_path), str(bundle), "-o", str(revealed),
         "--force", "--json"], context.work)
    width, height = config.big_secret
    return Measured([{"width": width, "height": height, "pixels": width * height, "tiles": len(hide["tiles"]),
                      "hide_seconds": hide_seconds, "hide_peak_mib": hide_peak, "driver_peak_mib": driver_peak,
                      "bundle_bytes": hide["bundle_bytes"], "bytes_per_pixel": hide["bytes_per_pixel"],
                      "reveal_seconds": reveal_seconds, "reveal_peak_mib": reveal_peak, "exact": reveal["exact"],
                      "hide_exact": hide["exact"]}])


def describe_big_secret(context: BenchContext, measured: Measured) -> list[str]:
    row = measured.rows[0]
    return [f"`{context.config.secret}` resized to {row['width']}×{row['height']} ({row['pixels'] / 1e6:.1f} MP), "
            f"hidden by `noisenerf hide` (local executor, every core) and revealed by `noisenerf-reveal` "
            f"(onnxruntime), each a process of its own.", "",
            f"- Hide: {row['hide_seconds'] / 60:.1f} min, {row['tiles']} tiles, {row['bytes_per_pixel']:.2f} bytes "
            f"per pixel; peak memory: driver **{row['driver_peak_mib']:.0f} MiB**, largest process "
            f"{row['hide_peak_mib']:.0f} MiB.",
            f"- Reveal: {row['reveal_seconds']:.1f} s, exact **{str(row['exact']).lower()}**, peak memory "
            f"**{row['reveal_peak_mib']:.0f} MiB**, of which the 8-bit secret is "
            f"{3 * row['pixels'] / 2 ** 20:.0f} MiB and the bundle's file "
            f"{row['bundle_bytes'] / 2 ** 20:.0f} MiB."]
