// A node:test reporter that writes one JSON line per finished test (passed, failed or skipped), so that
// tests/test_web.py can check which JavaScript cases ran, not only that `node --test` exited 0.
export default async function* eventsReporter(source) {
  for await (const event of source) {
    if (event.type === "test:pass" || event.type === "test:fail") {
      const { name, nesting, file, skip, todo } = event.data;
      yield `${JSON.stringify({ passed: event.type === "test:pass", name, nesting, file: file ?? null,
        skip: skip ?? false, todo: todo ?? false })}\n`;
    }
  }
}
