"""An 8K secret (7680×4320 by default) hidden and revealed by the two command-line tools, each in a
process of its own, with the memory each used: does it grow with the tile, not with the secret?

Peak memory is each process's high-water mark (VmHWM), read from /proc for the command and every process
it starts (the hide's local workers) while they run. Not wait4's ru_maxrss: a child's counts the memory
its parent had when it forked, here the bench's own. The hide uses the local executor on every core.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from noisenerf.runtime.images import write_image

from noisenerf.cli.bench.context import BenchContext, Measured, peak_sampled, resized

SAMPLE_SECONDS = 0.2  # how often the processes' high-water marks are read


def process_tree(pid: int) -> list[int]:
    """pid and every process it started that is still running."""
    found, stack = [], [pid]
    while stack:
        current = stack.pop()
        found.append(current)
        for task in Path(f"/proc/{current}/task").glob("*"):
            try:
                stack.extend(int(child) for child in (task / "children").read_text().split())
            except OSError:  # the task or process has gone
                continue
    return found


def high_water_mib(pid: int) -> float | None:
    """A running process's peak resident set (VmHWM) in MiB; None once it has gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    line = next((line for line in status.splitlines() if line.startswith("VmHWM:")), None)
    return None if line is None else int(line.split()[1]) / 1024


def run_measured(command: list[str], logs: Path) -> tuple[dict, float, float, float]:
    """Run a noisenerf command with --json -> its report, seconds, its own peak RSS (MiB) and the largest
    peak of the processes it started (MiB; 0 without any), as last sampled (a process's VmHWM only grows).
    Its output goes to files in `logs`. A command that fails stops the bench with its stderr."""
    started = time.perf_counter()
    with open(logs / "stdout", "w+") as stdout, open(logs / "stderr", "w+") as stderr:
        process = subprocess.Popen(command, stdout=stdout, stderr=stderr, text=True)
        with peak_sampled(lambda: high_water_mib(process.pid) or 0.0, SAMPLE_SECONDS) as own, \
                peak_sampled(lambda: max((high_water_mib(pid) or 0.0 for pid in process_tree(process.pid)[1:]),
                                         default=0.0), SAMPLE_SECONDS) as started_processes:
            process.wait()
        seconds = time.perf_counter() - started
        if process.returncode != 0:
            stderr.seek(0)
            raise RuntimeError(f"{' '.join(command[2:5])} failed ({process.returncode}): {stderr.read().strip()[-500:]}")
        stdout.seek(0)
        return json.loads(stdout.read()), seconds, own[0], started_processes[0]


def measure_big_secret(context: BenchContext) -> Measured:
    """The secret resized to config.big_secret, hidden with `noisenerf hide` and revealed with
    `noisenerf-reveal` (onnxruntime), each timed and its memory measured."""
    config = context.config
    photo = resized(context.secret, *config.big_secret)
    write_image(context.work / "big.png", photo)
    bundle, revealed = context.work / "big.bundle", context.work / "big_revealed.png"
    hide, hide_seconds, driver_peak, worker_peak = run_measured(
        [sys.executable, "-m", "noisenerf.cli.main", "hide", config.scene, str(context.work / "big.png"), "-o",
         str(bundle), "--view", str(config.view), "--force", "--json", "--quiet"], context.work)
    reveal, reveal_seconds, reveal_peak, _ = run_measured(
        [sys.executable, "-m", "noisenerf.cli.reveal", str(context.model_path), str(bundle), "-o", str(revealed),
         "--force", "--json"], context.work)
    width, height = config.big_secret
    return Measured([{"width": width, "height": height, "pixels": width * height, "tiles": len(hide["tiles"]),
                      "hide_seconds": hide_seconds, "driver_peak_mib": driver_peak, "worker_peak_mib": worker_peak,
                      "bundle_bytes": hide["bundle_bytes"], "bytes_per_pixel": hide["bytes_per_pixel"],
                      "reveal_seconds": reveal_seconds, "reveal_peak_mib": reveal_peak, "exact": reveal["exact"],
                      "hide_exact": hide["exact"]}])


def describe_big_secret(context: BenchContext, measured: Measured) -> list[str]:
    row = measured.rows[0]
    return [f"`{context.config.secret}` resized to {row['width']}×{row['height']} ({row['pixels'] / 1e6:.1f} MP), "
            f"hidden by `noisenerf hide` (local executor, every core) and revealed by `noisenerf-reveal` "
            f"(onnxruntime), each a process of its own.", "",
            f"- Hide: {row['hide_seconds'] / 60:.1f} min, {row['tiles']} tiles, {row['bytes_per_pixel']:.2f} bytes "
            f"per pixel; peak memory: driver **{row['driver_peak_mib']:.0f} MiB**, each worker at most "
            f"{row['worker_peak_mib']:.0f} MiB.",
            f"- Reveal: {row['reveal_seconds']:.1f} s, exact **{str(row['exact']).lower()}**, peak memory "
            f"**{row['reveal_peak_mib']:.0f} MiB**, of which the 8-bit secret is "
            f"{3 * row['pixels'] / 2 ** 20:.0f} MiB and the bundle's file "
            f"{row['bundle_bytes'] / 2 ** 20:.0f} MiB."]
