// The page's worker script runs in one of two roles, told apart by the name page.js starts it under.
export const REVEAL_WORKER = "noisenerf-reveal";
export const FIELD_WORKER = "noisenerf-field";
