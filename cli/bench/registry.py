"""Every bench experiment, in the order a run measures and reports them, and what each needs of the others."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable, Mapping

from noisenerf.runtime.errors import UserError

from noisenerf.cli.bench import (big_secret, browser, cluster, coverage, exact_cost, exact_scale, fields, ingp, keys,
                                 margins, masking, nerfstudio, paper, payload, reliability)
from noisenerf.cli.bench.context import BenchContext, Measured, Section


@dataclass(frozen=True)
class Experiment:
    """One experiment: it measures rows (its CSV), then describes them for the report. What it needs from
    other experiments it names in `needs` and reads from `context.needed`, by name, read-only."""

    name: str  # of its CSV and plot, and what --only takes
    title: str  # its report section's heading
    measure: Callable[[BenchContext], Measured]
    describe: Callable[[BenchContext, Any], list[str]]  # the report's lines, from what `measure` returned
    plot: Callable[[list[dict], Path], None] | None = None  # draws the rows as a PNG at the path given
    needs: tuple[str, ...] = ()  # experiments whose Measured it reads; REGISTRY lists them before it

    def run(self, context: BenchContext, earlier: Mapping[str, Measured]) -> tuple[Measured, Section]:
        """Measure and describe, given what the experiments run before measured (by name); it sees only its needs."""
        context = dataclasses.replace(context, needed=MappingProxyType({name: earlier[name] for name in self.needs}))
        measured = self.measure(context)
        return measured, Section(self.name, self.title, measured.rows, self.describe(context, measured))


# Each experiment comes after those it needs, so the registry's order runs needs first (test_bench checks it).
REGISTRY = (
    Experiment("paper_quality", "The paper's method at the paper's scale", paper.measure_paper_quality,
               paper.describe_paper_quality, paper.plot_paper_quality),
    Experiment("paper_changes", "The paper's method: our changes to its recipe, each switched off",
               paper.measure_paper_changes, paper.describe_paper_changes, needs=("paper_quality",)),
    Experiment("error_vs_time", "Run time against error: paper vs exact", paper.measure_error_vs_time,
               paper.describe_error_vs_time, paper.plot_error_vs_time),
    Experiment("ablation", "The paper's Table 3 ablation (paper mode)", paper.measure_ablation, paper.describe_ablation,
               paper.plot_ablation),
    Experiment("paper_speed", "The paper's method, skipping what cannot matter", paper.measure_paper_speed,
               paper.describe_paper_speed),
    Experiment("cost", "Hide ÷ reveal cost", exact_cost.measure_cost, exact_cost.describe_cost),
    Experiment("throughput", "Reveal throughput", exact_cost.measure_throughput, exact_cost.describe_throughput,
               needs=("cost",)),  # it reveals cost's bundle
    Experiment("skipping", "Skipping what the scene does not need", exact_cost.measure_skipping,
               exact_cost.describe_skipping),
    Experiment("bundle_size", "Bundle size", exact_cost.measure_bundle_size, exact_cost.describe_bundle_size,
               needs=("error_vs_time",)),  # it stores the paper's noise from there as float32 and float16
    Experiment("keys", "Keys against the secret's own coding", keys.measure_keys, keys.describe_keys),
    Experiment("photos", "Real photos at native size", exact_scale.measure_photos, exact_scale.describe_photos),
    Experiment("views", "Hide time across views and photos", exact_scale.measure_views, exact_scale.describe_views,
               exact_scale.plot_views),
    Experiment("contention", "Hide on a busy machine", exact_scale.measure_contention, exact_scale.describe_contention),
    Experiment("twok", "2K secrets as tiles", exact_scale.measure_twok, exact_scale.describe_twok),
    Experiment("coverage", "Exact everywhere: hard secrets at every camera", coverage.measure_coverage,
               coverage.describe_coverage),
    Experiment("payload", "File payloads, plain and sealed", payload.measure_payload, payload.describe_payload),
    Experiment("masking", "What a bundle shows without its model", masking.measure_masking, masking.describe_masking),
    Experiment("margins", "The rounding margin, and the arithmetic errors bundles survive", margins.measure_margins,
               margins.describe_margins),
    Experiment("reliability", "Hostile and failing conditions, by verdict", reliability.measure_reliability,
               reliability.describe_reliability),
    Experiment("browser", "Reveal in a browser", browser.measure_browser, browser.describe_browser),
    Experiment("cluster", "Hiding on Ray", cluster.measure_cluster, cluster.describe_cluster),
    Experiment("big_secret", "An 8K secret, and the memory it takes", big_secret.measure_big_secret,
               big_secret.describe_big_secret),
    Experiment("fields", "Field kinds: the MLP, the hash grid and nerfacto, fitted alike, hidden in alike", fields.measure_fields,
               fields.describe_fields, fields.plot_fields),
    Experiment("nerfstudio", "A nerfstudio run imported: its renders against nerfstudio's, secrets hidden in it",
               nerfstudio.measure_nerfstudio, nerfstudio.describe_nerfstudio),
    Experiment("ingp", "An Instant-NGP snapshot imported: its cost, secrets hidden in it", ingp.measure_ingp,
               ingp.describe_ingp),
)
EXPERIMENTS = tuple(experiment.name for experiment in REGISTRY)


def selected(names: tuple[str, ...] | None) -> tuple[Experiment, ...]:
    """The experiments named (BenchConfig.experiments; None: all of them) and every one they need, in the
    registry's order, which puts needs first. An experiment selected alone brings what it needs along, and
    the report has that section too: `--only throughput` measures cost first, as throughput reveals cost's
    bundle, rather than refusing or measuring less."""
    if names is None:
        return REGISTRY
    unknown = set(names) - set(EXPERIMENTS)
    if unknown:
        raise UserError(f"unknown experiments {sorted(unknown)} (choose from {', '.join(EXPERIMENTS)})")
    wanted = set(names)
    for experiment in reversed(REGISTRY):  # dependents before their needs, so needs of needs are added too
        if experiment.name in wanted:
            wanted.update(experiment.needs)
    return tuple(experiment for experiment in REGISTRY if experiment.name in wanted)
