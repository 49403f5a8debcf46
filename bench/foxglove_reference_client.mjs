// The run's Foxglove server seen by the protocol's reference client (npm @foxglove/ws-protocol),
// a second client independent of ours (tests/foxglove_client.py). docs/foxglove.md shows its output.
//
//   npm install @foxglove/ws-protocol ws      (in any folder; node 18 or later)
//   neoslam run --max-frames 300 --foxglove &
//   node bench/foxglove_reference_client.mjs ws://127.0.0.1:8765
//
// It offers the protocol's original subprotocol alone first (the name this client library and
// older viewers send), then with the foxglove-sdk's current name, subscribes to every channel,
// counts what comes per topic until the server closes, and prints the JSON records' last values.
import wsProtocol from "@foxglove/ws-protocol"; // a CommonJS package: its default export
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const url = process.argv[2] ?? "ws://127.0.0.1:8765";
const SDK_SUBPROTOCOL = "foxglove.sdk.v1";

function attempt(protocols) {
  return new Promise((resolve) => {
    const ws = new WebSocket(url, protocols);
    ws.on("error", (err) => resolve({ ok: false, error: String(err.message ?? err) }));
    ws.on("open", () => resolve({ ok: true, ws }));
  });
}

let first = await attempt([FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
for (let i = 0; !first.ok && first.error.includes("ECONNREFUSED") && i < 600; i++) {
  await new Promise((r) => setTimeout(r, 200)); // the server is not up yet
  first = await attempt([FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
}
console.log(`subprotocol ${FoxgloveClient.SUPPORTED_SUBPROTOCOL} alone: ${first.ok ? "accepted" : first.error}`);
if (first.ok) first.ws.close();

const socket = new WebSocket(url, [SDK_SUBPROTOCOL, FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws: socket });
const channels = new Map(); // subscription id -> channel
const counts = new Map(); // topic -> [messages, bytes]
const last = new Map(); // topic -> last JSON record
const decoder = new TextDecoder();

client.on("open", () => console.log(`connected to ${url} with subprotocol ${socket.protocol}`));
client.on("serverInfo", (info) =>
  console.log(`server "${info.name}", capabilities [${info.capabilities.join(", ")}]`));
client.on("status", (s) => console.log(`status (level ${s.level}): ${s.message}`));
client.on("advertise", (advertised) => {
  for (const ch of advertised) {
    channels.set(client.subscribe(ch.id), ch);
    console.log(`  ${ch.topic.padEnd(22)} ${ch.encoding.padEnd(9)} ${ch.schemaName}`);
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const ch = channels.get(subscriptionId);
  const [n, bytes] = counts.get(ch.topic) ?? [0, 0];
  counts.set(ch.topic, [n + 1, bytes + data.byteLength]);
  if (ch.encoding === "json") last.set(ch.topic, JSON.parse(decoder.decode(data)));
});
client.on("close", () => {
  console.log("server closed the connection; messages per topic:");
  for (const [topic, [n, bytes]] of [...counts].sort()) {
    console.log(`  ${topic.padEnd(22)} ${String(n).padStart(5)} messages ${String(bytes).padStart(9)} bytes`);
  }
  for (const topic of ["/neoslam/run", "/neoslam/loop_closure", "/neoslam/stats"]) {
    if (last.has(topic)) console.log(`last ${topic}: ${JSON.stringify(last.get(topic))}`);
  }
});
