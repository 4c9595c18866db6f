"""Independent check of an episode recording with the `mcap` Python package.

Reads FILE with mcap's own reader (not our Rust code), decodes every message as JSON,
validates each `foxglove.*` message against Foxglove's published JSON schema (fetched from
npm by scripts/fetch_foxglove_schemas.sh) and each `equact.*` message against the schema
stored in the file, then prints a JSON summary: {"complete", "counts", "outcome", "errors", "median_period_s"}
(the median gap between log times per topic).

With --truncated the file may end anywhere: it is read record by record with mcap's
stream reader until the data runs out, and only complete chunks count.
"""
import argparse
import json
import os
import struct
import sys

import jsonschema
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.exceptions import McapError


def load_official(schema_dir):
    out = {}
    for name in os.listdir(schema_dir):
        if name.endswith(".json"):
            with open(os.path.join(schema_dir, name)) as f:
                out["foxglove." + name[:-5]] = json.load(f)
    return out


def validator_for(schema_name, embedded, official):
    if schema_name.startswith("foxglove."):
        if schema_name not in official:
            raise SystemExit(f"no official Foxglove schema named {schema_name}")
        schema = official[schema_name]
    else:
        schema = json.loads(embedded)
    return jsonschema.Draft7Validator(schema)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("file")
    ap.add_argument("--schemas", required=True, help="folder of Foxglove's JSON schemas")
    ap.add_argument("--truncated", action="store_true")
    args = ap.parse_args()
    official = load_official(args.schemas)

    counts, errors, outcome = {}, [], None
    times = {}
    validators = {}
    complete = False

    def handle(channel, schema, data, log_time):
        nonlocal outcome
        key = channel.topic
        if key not in validators:
            validators[key] = validator_for(schema.name, schema.data.decode(), official)
        msg = json.loads(data)
        for err in validators[key].iter_errors(msg):
            errors.append(f"{key}: {err.message[:200]}")
        counts[key] = counts.get(key, 0) + 1
        times.setdefault(key, []).append(log_time)
        if key == "/episode/outcome":
            outcome = msg

    with open(args.file, "rb") as f:
        if not args.truncated:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages():
                handle(channel, schema, message.data, message.log_time)
            complete = reader.get_summary() is not None
        else:
            schemas, channels = {}, {}
            try:
                for record in StreamReader(f, skip_magic=False).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message):
                        ch = channels[record.channel_id]
                        handle(ch, schemas[ch.schema_id], record.data, record.log_time)
            except (McapError, EOFError, ValueError, KeyError, struct.error) as e:
                errors.append(f"stream ended: {type(e).__name__}")
    median_period_s = {}
    for key, ts in times.items():
        gaps = sorted(b - a for a, b in zip(ts, ts[1:]) if b > a)
        if gaps:
            median_period_s[key] = gaps[len(gaps) // 2] * 1e-9
    print(json.dumps({"complete": complete, "counts": counts, "outcome": outcome, "errors": errors,
                      "median_period_s": median_period_s}))


if __name__ == "__main__":
    sys.exit(main())
