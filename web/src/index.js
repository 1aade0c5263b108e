// The stable API: `await reveal({model, bundle, passphrase})`, the browser's `noisenerf-reveal` (cli/reveal.py):
// the bundle is read and checked first, then the model (graph and fingerprint), then the bundle against the
// model, then every tile renders. Every refusal is an Error (UserError) with the CLI's one-line message.

import { UserError } from "./errors.js";
import { loadBundle } from "./bundle.js";
import { checkModel, checkBundle } from "./model.js";
import { OnnxField, revealBundle } from "./reveal.js";
import { encodePng } from "./png.js";

export { UserError } from "./errors.js";
export const PAYLOADS_NOT_YET = "this version of the page does not reveal payloads yet (a file or sealed bundle): " +
  "use noisenerf-reveal";

/**
 * model, bundle: Uint8Array; passphrase: string (sealed bundles, not yet supported).
 * -> {kind: "image", bytes (PNG), name, width, height, exact, sha256, pixels}
 */
export async function reveal({ model, bundle, passphrase = null, onProgress = null, sessionOptions = {} }) {
  if (!(model instanceof Uint8Array) || !(bundle instanceof Uint8Array)) throw new TypeError("model and bundle must be Uint8Arrays");
  const secret = await loadBundle(bundle, "secret.bundle");
  if (secret.payload !== null) throw new UserError(PAYLOADS_NOT_YET);
  const checked = checkModel(model, "model.onnx");
  checkBundle(checked, secret);
  const field = await OnnxField.create(model, checked.networks, sessionOptions);
  try {
    const revealed = await revealBundle(secret, checked.metadata.renderConfig, field, onProgress);
    return { kind: "image", bytes: encodePng(revealed.pixels, secret.width, secret.height), name: "revealed.png",
      width: secret.width, height: secret.height, exact: revealed.exact, sha256: revealed.sha256, pixels: revealed.pixels,
      image: revealed.image };
  } finally {
    await field.session.release?.();
  }
}
