#!/usr/bin/env bash
# Fetches Foxglove's published JSON schemas (npm package @foxglove/schemas) into
# .venv/foxglove-schemas/<Name>.json, so the test suite can check our recordings against
# Foxglove's own definitions rather than our copy of them.
set -euo pipefail
cd "$(dirname "$0")/.."
version=2.1.0
out=.venv/foxglove-schemas
[ -f "$out/.version" ] && [ "$(cat "$out/.version")" = "$version" ] && exit 0
command -v npm >/dev/null && command -v node >/dev/null || {
  echo "fetch_foxglove_schemas: node and npm are needed (Debian: apt-get install nodejs npm)" >&2; exit 1; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "@foxglove/schemas@$version" >/dev/null 2>&1 && tar xzf foxglove-schemas-$version.tgz)
mkdir -p "$out"
node -e '
const s = require(process.argv[1] + "/package/dist/jsonschema/index.js");
const fs = require("fs");
for (const [name, schema] of Object.entries(s)) fs.writeFileSync(process.argv[2] + "/" + name + ".json", JSON.stringify(schema));
' "$tmp" "$out"
echo "$version" > "$out/.version"
echo "fetch_foxglove_schemas: $(ls "$out" | wc -l) schemas in $out"
