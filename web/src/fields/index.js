// Mirrors runtime/fields/__init__.py: the field kinds a scene's networks may be, one registered kind per
// architecture family (a network whose architecture names no "kind" is an `mlp`). A kind owns its architecture's
// keys and caps (`checked`, refusing with Python's codes and params), its noise segments (`segments`), its part of the graph
// (`build`) and the opset that part needs, and its proposal sampler (`proposalSampler`: null for a field rendered
// with the scene's own sampling; nerfacto's proposal networks are outputs sigma_proposal0, …); `fieldGraph` composes
// a model's networks into the one graph check_graph (src/graph.js) binds the model file to.

import { UserError, cut, show } from "../errors.js";
import { isJsonObject } from "../json.js";
import { COARSE_OUTPUT_NAMES, OUTPUT_NAMES, BATCH, GraphBuilder, port, proposalOutput } from "../graph.js";
import { MLP } from "./mlp.js";
import { HASHGRID } from "./hashgrid.js";
import { NERFACTO } from "./nerfacto.js";

export const DEFAULT_KIND = "mlp";

/** A field kind: its name, opset, `checked`, `segments` and `build`, and what it does not override of the defaults
 * (FieldKind's in Python): `proposalSampler` null, for a field rendered with the scene's own sampling. */
const fieldKindOf = (kind) => ({ proposalSampler: () => null, ...kind });

/** A named run of a network's noise vector: `dims` values added to the encoding called `name`. */
export const segment = (name, dims) => ({ name, dims });

/** True when `config` is a JSON object whose keys are exactly `keys` (Python's `set(config) != KEYS`). */
export const hasExactly = (config, keys) => isJsonObject(config) && Object.keys(config).length === keys.length &&
  keys.every((key) => Object.hasOwn(config, key));

/** Every registered kind by name (built on each call, as Python's: the kinds import this module). */
export function fieldKinds() {
  return Object.fromEntries([MLP, HASHGRID, NERFACTO].map((kind) => [kind.name, fieldKindOf(kind)]));
}

/** field_kind: the kind an architecture names (an `mlp` where it names none); an unknown one is refused. */
export function fieldKind(config, what) {
  const name = isJsonObject(config) && Object.hasOwn(config, "kind") ? config.kind : DEFAULT_KIND;
  const kinds = fieldKinds();
  if (typeof name !== "string" || !Object.hasOwn(kinds, name)) {
    throw new UserError(`the ${what} network is of kind ${show(name)}; this noisenerf knows ${Object.keys(kinds).sort().join(", ")}`,
      { code: "field.unknown_kind", network: what, kind: typeof name === "string" ? cut(name) : null });
  }
  return kinds[name];
}

/** field_graph: the graph of a model with this architecture ({coarse, fine: … | null}) and noise width: outputs
 * rgb, sigma of the render network (the fine one where there is one), then rgb_coarse, sigma_coarse beside a fine
 * network, then sigma_proposal0, … of the render network's proposal networks; the opset is the highest its kinds
 * need. Refuses an architecture out of the caps, or proposal networks beside a fine network (UserError). */
export function fieldGraph(architecture, noiseWidth) {
  const builder = new GraphBuilder();
  const kinds = {}, checked = {};
  for (const [name, config] of Object.entries(architecture)) if (config !== null) kinds[name] = fieldKind(config, name);
  for (const [name, kind] of Object.entries(kinds)) checked[name] = kind.checked(architecture[name], name);
  const outputs = [port("rgb", [BATCH, 3]), port("sigma", [BATCH])];
  if (!Object.hasOwn(checked, "fine")) kinds.coarse.build(builder, "coarse", checked.coarse, ...OUTPUT_NAMES);
  else {
    kinds.fine.build(builder, "fine", checked.fine, ...OUTPUT_NAMES);
    kinds.coarse.build(builder, "coarse", checked.coarse, ...COARSE_OUTPUT_NAMES);
    outputs.push(port("rgb_coarse", [BATCH, 3]), port("sigma_coarse", [BATCH]));
  }
  const samplers = Object.fromEntries(Object.entries(kinds).map(([name, kind]) => [name, kind.proposalSampler(checked[name])]));
  if (Object.values(samplers).some((sampler) => sampler !== null) && Object.hasOwn(checked, "fine")) {
    throw new UserError("a network with proposal networks cannot be beside a fine network", { code: "field.proposals_beside_fine" });
  }
  if (samplers.coarse !== null) outputs.push(...samplers.coarse.proposal_samples.map((_, i) => port(proposalOutput(i), [BATCH])));
  const inputs = [port("points", [BATCH, 3]), port("viewdirs", [BATCH, 3]), port("noise", [BATCH, noiseWidth])];
  return { nodes: builder.nodes, constants: builder.constants, weights: builder.weights, inputs, outputs,
    opset: Math.max(...Object.values(kinds).map((kind) => kind.opset)) };
}
