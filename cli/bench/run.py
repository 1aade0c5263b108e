"""A whole bench run: the selected experiments and those they need, in the registry's order, then CSVs,
plots and the report."""

from __future__ import annotations

import tempfile
from pathlib import Path

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import load_secret
from noisenerf.runtime.model import load_model
from noisenerf.train.scene.scene import load_scene

from noisenerf.cli.bench import stress
from noisenerf.cli.bench.config import BenchConfig
from noisenerf.cli.bench.context import BenchContext, Section, timed
from noisenerf.cli.bench.registry import REGISTRY, selected
from noisenerf.cli.bench.report import write_csv, write_report


def run_bench(config: BenchConfig, out: Path, run_stress: bool, command: str, progress=print) -> list[Section]:
    """Run the configured experiments and those they need (registry.selected); write OUT/BENCHMARKS.md, CSVs
    and plots. Returns the sections."""
    from noisenerf.export.onnx_export import export_scene

    experiments = selected(config.experiments)
    if not out.parent.is_dir():
        raise UserError(f"output folder does not exist: {out.parent}")
    out.mkdir(exist_ok=True)
    scene = load_scene(config.scene)
    secret, _, _ = load_secret(config.secret)
    sections = []
    with tempfile.TemporaryDirectory() as tmp:
        model_path = Path(tmp) / "model.onnx"
        export_scene(config.scene, model_path)
        context = BenchContext(config, scene, secret, Path(tmp), model_path, load_model(model_path))
        measured = {}  # the runner's own: an experiment gets a read-only view of its needs only
        for experiment in experiments:
            dependents = [other.name for other in experiments if experiment.name in other.needs]
            asked = config.experiments is None or experiment.name in config.experiments
            progress(f"bench: {experiment.name}" + ("" if asked else f" (needed by {', '.join(dependents)})"))
            (measured[experiment.name], section), seconds = timed(experiment.run, context, measured)
            section.lines.append(f"\n_(experiment wall time {seconds:.0f} s)_")
            sections.append(section)
    if run_stress:
        progress("bench: stress")
        sections.append(stress_section())
    for section in sections:
        write_csv(out / f"{section.name}.csv", section.rows)
    plot_sections(sections, out)
    write_report(out / "BENCHMARKS.md", config, sections, command)
    return sections


def plot_sections(sections: list[Section], out: Path) -> None:
    """PNG plots beside the report, OUT/<name>.png, for the experiments that have curves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots = {experiment.name: experiment.plot for experiment in REGISTRY if experiment.plot}
    for section in sections:
        if section.name in plots:
            plots[section.name](section.rows, out / f"{section.name}.png")
            section.plots.append(f"{section.name}.png")
    plt.close("all")


def stress_section() -> Section:
    """Every case of the numerical stress checks (stress.py), one row each; the report lists the failures."""
    rows, seconds = timed(stress.run_stress)
    failed = [row for row in rows if not row["passed"]]
    lines = [f"Every case of the numerical stress checks (`cli/bench/stress.py`, on a small random-weight scene; "
             f"`NOISENERF_STRESS=full pytest tests/test_stress.py` runs the same): **{len(rows) - len(failed)} of "
             f"{len(rows)} passed** ({seconds:.0f} s)."]
    if failed:
        lines += ["", *(f"- failed: `{row['case']}`: {row['error']}" for row in failed)]
    return Section("stress", "Numerical stress suite", rows, lines)
