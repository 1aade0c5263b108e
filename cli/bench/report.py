"""What a bench run writes: the goal verdicts, CSVs, PNG plots and BENCHMARKS.md."""

from __future__ import annotations

import csv
import datetime
import platform
from pathlib import Path

import onnxruntime
import torch

import noisenerf
from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.files import atomic_output

from noisenerf.cli.bench.config import BenchConfig
from noisenerf.cli.bench.context import Section


def verdict(value: float, goal: float, lower_is_better: bool, also: bool = True) -> str:
    """"met" when value reaches the goal (equal counts) and `also`, a second condition some goals add, holds."""
    reached = value <= goal if lower_is_better else value >= goal
    return "met" if reached and also else "not met"


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    if Path("/proc/cpuinfo").is_file():
        names = [line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                 if line.startswith("model name")]
        cpu = names[0] if names else cpu
    return {"cpu": cpu, "cores": available_cores(),
            "python": platform.python_version(), "torch": torch.__version__, "onnxruntime": onnxruntime.__version__,
            "noisenerf": noisenerf.__version__}


def curves_plot(rows: list[dict], path: Path, group: str, x: str, y: str, labels: tuple[str, str], marker: str = ".",
                size: tuple[float, float] = (5, 3.6)) -> None:
    """One line per value of `group` in the rows, y against x."""
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=size)
    for value in dict.fromkeys(r[group] for r in rows):
        curve = [r for r in rows if r[group] == value]
        axis.plot([r[x] for r in curve], [r[y] for r in curve], marker=marker, label=value)
    axis.set_xlabel(labels[0])
    axis.set_ylabel(labels[1])
    axis.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def save_figure(figure, path: Path) -> None:
    with atomic_output(path, replace=True) as tmp:
        figure.savefig(tmp, dpi=90, format="png")


def write_csv(path: Path, rows: list[dict]) -> None:
    keys = list(dict.fromkeys(key for row in rows for key in row))
    with atomic_output(path, replace=True) as tmp, open(tmp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, keys)
        writer.writeheader()
        writer.writerows(rows)


def write_report(path: Path, config: BenchConfig, sections: list[Section], command: str) -> None:
    info = machine()
    lines = ["# noisenerf benchmarks", "",
             f"Regenerate with `{command}` (from the repository root; the scene is fitted as the README's "
             "Benchmarks section says).", "",
             f"Machine: {info['cpu']}, {info['cores']} cores; Python {info['python']}, torch {info['torch']}, "
             f"onnxruntime {info['onnxruntime']}, noisenerf {info['noisenerf']}; "
             f"{datetime.date.today().isoformat()}. Absolute times are this machine's; ratios are measured side by "
             "side in the same run.", "",
             f"Scene `{config.scene}`, secret `{Path(config.secret).name}`, view {config.view}.", ""]
    for section in sections:
        lines += [f"## {section.title}", "", *section.lines, ""]
        lines += [f"![{section.title}]({plot})" for plot in section.plots]
        lines += [f"Data: [{section.name}.csv]({section.name}.csv)", ""]
    with atomic_output(path, replace=True) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
