// Runs the Foxglove apps' JSON Schema converter (`parseJsonSchema` of the apps'
// mcap-support package, as shipped in the npm package @foxglove/studio-base) on channel
// schemas: the way Foxglove / Lichtblick decide whether a `jsonschema` channel can be
// subscribed.  Used by tests/test_foxglove_converter.py, which installs the package.
//
//   node parse_json_schemas.js BUNDLE.js < [{"topic", "schemaName", "schema"}, ...]
//   -> {"TOPIC": {"ok": true, "types": N} | {"ok": false, "error": "..."}, ...}
"use strict";
const fs = require("fs");

const MODULE = ";// CONCATENATED MODULE: ../mcap-support/src/parseJsonSchema.ts";
const bundle = fs.readFileSync(process.argv[2], "utf8");
const start = bundle.indexOf(MODULE);
// the module ends where the bundle declares the next one (or its next import)
const end = Math.min(
  ...[";// CONCATENATED MODULE:", "// EXTERNAL MODULE:"]
    .map((m) => bundle.indexOf(m, start + MODULE.length))
    .filter((i) => i >= 0),
);
if (start < 0 || !Number.isFinite(end)) {
  throw new Error(`parseJsonSchema module not found in ${process.argv[2]}`);
}
const source = bundle.slice(start + MODULE.length, end);
// the module's one import, @protobufjs/base64 (installed next to the bundle's package),
// is the bundle's `base64` variable
const base64 = require("module").createRequire(process.argv[2])("@protobufjs/base64");
const parseJsonSchema = new Function("base64", `${source}\nreturn parseJsonSchema;`)(base64);

const channels = JSON.parse(fs.readFileSync(0, "utf8"));
const out = {};
for (const { topic, schemaName, schema } of channels) {
  try {
    const { datatypes } = parseJsonSchema(JSON.parse(schema), schemaName);
    out[topic] = { ok: true, types: datatypes.size };
  } catch (err) {
    out[topic] = { ok: false, error: String(err && err.message ? err.message : err) };
  }
}
process.stdout.write(JSON.stringify(out));
