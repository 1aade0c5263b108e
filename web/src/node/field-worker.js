// A field worker in Node (worker_threads), as src/page/worker.js is one in the page: ./pool.js starts these.
import { parentPort } from "node:worker_threads";
import { fieldWorker } from "../pool.js";

const answer = fieldWorker();
parentPort.on("message", async (data) => {
  const [reply, transfer] = await answer(data);
  parentPort.postMessage(reply, transfer);
});
