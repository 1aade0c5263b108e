// A refusal compared with the one Python raised (tests/test_web.py writes code, params and Python's message):
// the same code and params; the message only has to be one line of its own.

import assert from "node:assert/strict";
import { UserError } from "../src/errors.js";

export function sameRefusal(error, want) {
  assert.ok(error instanceof UserError, `not a UserError: ${error?.stack ?? error}`);
  assert.deepEqual({ code: error.code, params: error.params }, { code: want.code, params: want.params },
    `refused otherwise than Python (${want.message}): ${error.message}`);
  assert.ok(error.message.length > 0 && !error.message.includes("\n"), `not one line: ${JSON.stringify(error.message)}`);
  return true;
}
