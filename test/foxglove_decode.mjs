// Decode an MCAP recording with Foxglove's own libraries, as Foxglove Studio reads a file:
// @mcap/core's indexed reader, @foxglove/rosmsg to parse each channel's ros2msg schema, and
// @foxglove/rosmsg2-serialization to decode each message's CDR bytes.
//
// usage: node foxglove_decode.mjs FILE.mcap   (NODE_PATH or a node_modules beside it)
// prints one JSON object: {"counts": {topic: decoded messages}, "markers": [summary of each
// visualization_msgs/msg/MarkerArray: [ns, id, type, frame_locked, points] per marker]}.
import { open } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";

const require = createRequire(path.join(process.env.FOXGLOVE_MODULES ?? process.cwd(), "x.js"));
const { McapIndexedReader } = require("@mcap/core");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");

const file = process.argv[2];
const handle = await open(file, "r");
const size = BigInt((await handle.stat()).size);
const readable = {
  size: async () => size,
  read: async (offset, length) => {
    const out = new Uint8Array(Number(length));
    await handle.read(out, 0, Number(length), Number(offset));
    return out;
  },
};
const reader = await McapIndexedReader.Initialize({ readable });
const readers = new Map();
for (const [id, channel] of reader.channelsById) {
  const schema = reader.schemasById.get(channel.schemaId);
  if (schema.encoding !== "ros2msg" || channel.messageEncoding !== "cdr") {
    throw new Error(`${channel.topic}: ${schema.encoding}/${channel.messageEncoding}`);
  }
  const text = new TextDecoder().decode(schema.data);
  readers.set(id, { topic: channel.topic, type: schema.name,
                    reader: new MessageReader(parse(text, { ros2: true })) });
}
const counts = {};
const markers = [];
for await (const message of reader.readMessages()) {
  const { topic, type, reader: decoder } = readers.get(message.channelId);
  const decoded = decoder.readMessage(message.data);
  counts[topic] = (counts[topic] ?? 0) + 1;
  if (type === "visualization_msgs/msg/MarkerArray") {
    markers.push(decoded.markers.map((m) => [m.ns, m.id, m.type, m.frame_locked,
      m.points.map((p) => [p.x, p.y, p.z])]));
  }
}
await handle.close();
console.log(JSON.stringify({ counts, markers }));
