#!/usr/bin/env bash
# Refresh Foxglove's official JSON Schemas from the npm package @foxglove/schemas.
# The package ships them as JS objects (dist/jsonschema/index.js), so node dumps them to JSON.
# Usage: bash schemas/foxglove/fetch.sh [VERSION]   (default 2.1.0)
set -euo pipefail
version="${1:-2.1.0}"
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
(cd "$work" && npm pack --silent "@foxglove/schemas@${version}" >/dev/null && tar xzf ./*.tgz)
OUT="$here" SRC="$work/package/dist/jsonschema/index.js" node -e '
const fs = require("fs");
const schemas = require(process.env.SRC);
for (const [name, schema] of Object.entries(schemas)) {
  fs.writeFileSync(`${process.env.OUT}/${name}.json`, JSON.stringify(schema, null, 2) + "\n");
}
console.log(`${Object.keys(schemas).length} schemas written`);
'
echo "@foxglove/schemas ${version}" > "$here/VERSION"
