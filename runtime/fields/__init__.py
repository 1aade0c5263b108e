"""Field kinds: the networks a scene may hold, one registered kind per architecture family.

A network's architecture (scene.json, the model's metadata, and through the fingerprint every bundle)
names its kind under "kind"; a network without one is an `mlp` (the standard NeRF MLP, whose
architecture was written before kinds existed, so its fingerprints and graphs stay what they were). A
kind owns, torch-free: its architecture's keys and caps (`checked`), its noise as named segments
(`segments`: the position segment the trunk reads, then the direction segment the colour head reads),
its part of the graph (`build`: every node, constant and weight of one network, from noisy inputs to its
rgb and sigma outputs) and the opset that part needs. Its torch twin is train.scene.field_kinds.

`field_graph` composes a model's networks into the one graph the export writes and the reveal checks
(runtime.graph.check_graph); web/src/fields/ mirrors this package.
"""

from __future__ import annotations

from dataclasses import dataclass
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.graph import (
    BATCH, COARSE_OUTPUT_NAMES, OUTPUT_NAMES, FieldGraph, GraphBuilder, Port, proposal_output,
)

DEFAULT_KIND = "mlp"  # the kind of a network whose architecture names none


@dataclass(frozen=True)
class Segment:
    """A named run of a network's noise vector: `dims` values added to the encoding called `name`."""

    name: str  # "position" (read by the trunk) or "direction" (read by the colour head alone)
    dims: int


class FieldKind:
    """What every field kind is: a name, the opset its graph part needs, and the methods below; a kind subclasses
    this and overrides what it has (a kind rendered with the scene's own sampling keeps proposal_sampler's None)."""

    name: str
    opset: int  # the default domain's opset its graph needs

    def checked(self, config, what: str) -> dict:
        """The architecture as metadata states it, every number within the caps (UserError otherwise)."""
        raise NotImplementedError

    def segments(self, config: dict) -> tuple[Segment, ...]:
        """The noise segments of a checked architecture, in the noise vector's order."""
        raise NotImplementedError

    def build(self, builder: GraphBuilder, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        """One network of a checked architecture: noisy encodings of the `points`, `viewdirs` and `noise`
        inputs through its layers (weights named `prefix.…`) to the outputs rgb (n, 3) and sigma (n,), and
        one density output per proposal network (proposal_sampler)."""
        raise NotImplementedError

    def grid_sampler(self, config: dict) -> dict | None:
        """A checked architecture's occupancy-grid marcher for ordinary renders (runtime.grid_marching's fields);
        None where the kind has none."""
        return None

    def proposal_sampler(self, config: dict) -> dict | None:
        """A checked architecture's proposal sampler (runtime.proposal.ProposalSampling's fields), one stage
        per proposal network (outputs sigma_proposal0, …: density alone, no noise); None for a field
        rendered with the scene's own sampling."""
        return None


def field_kinds() -> dict[str, FieldKind]:
    """Every registered kind by name: the one list of kinds (imported here, not at the top: the kinds import this
    module). web/src/fields/index.js and train/scene/field_kinds.py register the same names (tests tie them)."""
    from noisenerf.runtime.fields.hashgrid import HASHGRID
    from noisenerf.runtime.fields.mlp import MLP
    from noisenerf.runtime.fields.nerfacto import NERFACTO
    return {kind.name: kind for kind in (MLP, HASHGRID, NERFACTO)}


def proposal_sampler(architecture: dict) -> dict | None:
    """The proposal sampler of a (graph-checked) architecture's render network, if its kind has one."""
    kind = field_kind(architecture["coarse"], "coarse")
    return kind.proposal_sampler(kind.checked(architecture["coarse"], "coarse"))


def grid_sampler(architecture: dict) -> dict | None:
    """The occupancy-grid marcher of a (graph-checked) architecture's render network, if its kind has one."""
    kind = field_kind(architecture["coarse"], "coarse")
    return kind.grid_sampler(kind.checked(architecture["coarse"], "coarse"))


def field_kind(config, what: str) -> FieldKind:
    """The kind an architecture names (an `mlp` where it names none); an unknown one is refused."""
    name = config.get("kind", DEFAULT_KIND) if isinstance(config, dict) else DEFAULT_KIND
    kinds = field_kinds()
    if not isinstance(name, str) or name not in kinds:
        raise UserError(f"the {what} network is of kind {name!r}; this noisenerf knows {sorted(kinds)}",
                        code="field.unknown_kind", network=what, kind=name[:60] if isinstance(name, str) else None)
    return kinds[name]


def field_graph(architecture: dict, noise_dims: int) -> FieldGraph:
    """The graph of a model with this architecture ({"coarse": architecture, "fine": … | None}) and
    noise width: outputs rgb, sigma of the render network (the fine one where there is one), then
    rgb_coarse, sigma_coarse beside a fine network, then sigma_proposal0, … of the render network's proposal
    networks. Refuses an architecture out of the caps (UserError)."""
    builder = GraphBuilder()
    kinds = {name: field_kind(config, name) for name, config in architecture.items() if config is not None}
    checked = {name: kind.checked(architecture[name], name) for name, kind in kinds.items()}
    outputs = [Port("rgb", (BATCH, 3)), Port("sigma", (BATCH,))]
    if "fine" not in checked:
        kinds["coarse"].build(builder, "coarse", checked["coarse"], *OUTPUT_NAMES)
    else:
        kinds["fine"].build(builder, "fine", checked["fine"], *OUTPUT_NAMES)
        kinds["coarse"].build(builder, "coarse", checked["coarse"], *COARSE_OUTPUT_NAMES)
        outputs += [Port("rgb_coarse", (BATCH, 3)), Port("sigma_coarse", (BATCH,))]
    samplers = {name: kind.proposal_sampler(checked[name]) for name, kind in kinds.items()}
    if any(samplers.values()) and "fine" in checked:
        raise UserError("a network with proposal networks cannot be beside a fine network",
                        code="field.proposals_beside_fine")
    if samplers["coarse"]:
        outputs += [Port(proposal_output(i), (BATCH,)) for i in range(len(samplers["coarse"]["proposal_samples"]))]
    inputs = (Port("points", (BATCH, 3)), Port("viewdirs", (BATCH, 3)), Port("noise", (BATCH, noise_dims)))
    return FieldGraph(tuple(builder.nodes), builder.constants, builder.weights, inputs, tuple(outputs),
                      max(kind.opset for kind in kinds.values()))
