#!/usr/bin/env python3
"""Checks Fresa's OpenAPI description with real validators (used by tests/clients/openapi.rs).

    openapi_check.py DOC.json [RESPONSES.json]

DOC.json is validated with `openapi-spec-validator` (OpenAPI 3.1). RESPONSES.json, if given, is a
list of {"operation", "path", "method", "status", "body"} recorded from a running server: each
JSON body is validated with `jsonschema` (Draft 2020-12, what OpenAPI 3.1 schemas are) against the
schema the document gives for that operation and status. Prints one line per problem; exit 1 if
any. Exit 3 when the validator is not installed, naming the pip command.
"""

import json
import sys

try:
    import jsonschema
    from openapi_spec_validator import validate
except ImportError as e:  # the Rust test turns this into a failure naming the install command
    print(f"missing Python package ({e}): pip install openapi-spec-validator", file=sys.stderr)
    sys.exit(3)


def response_schema(doc, path, method, status):
    op = doc["paths"][path][method]
    resp = op["responses"].get(str(status))
    if resp is None:
        return None, f"{method.upper()} {path}: status {status} is not documented"
    content = resp.get("content", {}).get("application/json")
    if content is None:
        return None, None
    # The schema at the root, with the document's components beside it so `#/components/...`
    # references resolve.
    schema = dict(content["schema"])
    schema["components"] = doc.get("components", {})
    return schema, None


def main():
    doc = json.load(open(sys.argv[1]))
    problems = []
    try:
        validate(doc)
    except Exception as e:  # noqa: BLE001 - report whatever the validator found
        problems.append(f"the document is not valid OpenAPI: {e}")
    if len(sys.argv) > 2:
        checked = 0
        for r in json.load(open(sys.argv[2])):
            schema, problem = response_schema(doc, r["path"], r["method"], r["status"])
            if problem:
                problems.append(problem)
                continue
            if schema is None:
                continue
            validator = jsonschema.Draft202012Validator(schema)
            for err in validator.iter_errors(r["body"]):
                where = "/".join(str(p) for p in err.absolute_path)
                problems.append(
                    f"{r['method'].upper()} {r['path']} {r['status']}: body at /{where}: {err.message}"
                )
            checked += 1
        print(f"{checked} response bodies checked against their schema")
    for p in problems:
        print(p)
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
