"""How many CPUs this process may use: the one count behind thread and worker defaults."""

from __future__ import annotations

import os


def available_cores() -> int:
    """CPUs this process may run on (honours taskset / cgroup affinity where the OS exposes it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
