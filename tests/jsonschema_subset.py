"""A validator for the subset of JSON Schema that ``bams_cli.schemas_json`` uses.

jsonschema is not a dependency; these few keywords are enough to hold each command's
``--json`` output to its schema. A keyword outside the subset is an error, so a schema can
never pass because the validator skipped what it could not read.
"""

from __future__ import annotations

from typing import Any

KNOWN = {
    "$schema", "$id", "title", "description",  # annotations
    "type", "required", "properties", "additionalProperties", "items", "const", "enum",
    "minimum",
}  # fmt: skip

_TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    "integer": lambda v: (
        (isinstance(v, int) and not isinstance(v, bool))
        or (isinstance(v, float) and v.is_integer())
    ),
}


def errors(instance: Any, schema: dict[str, Any], path: str = "$") -> list[str]:
    """Every way ``instance`` breaks ``schema``, as ``path: problem`` lines (empty: valid)."""
    unknown = set(schema) - KNOWN
    if unknown:
        raise ValueError(f"{path}: schema keywords outside the subset: {sorted(unknown)}")
    out: list[str] = []
    if "type" in schema:
        kinds = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_TYPES[k](instance) for k in kinds):
            return [f"{path}: expected {' or '.join(kinds)}, got {instance!r:.60}"]
    if "const" in schema and instance != schema["const"]:
        out.append(f"{path}: expected {schema['const']!r}, got {instance!r:.60}")
    if "enum" in schema and instance not in schema["enum"]:
        out.append(f"{path}: expected one of {schema['enum']}, got {instance!r:.60}")
    if "minimum" in schema and isinstance(instance, int | float) and instance < schema["minimum"]:
        out.append(f"{path}: {instance} is below the minimum {schema['minimum']}")
    if isinstance(instance, dict):
        props = schema.get("properties", {})
        for key in schema.get("required", []):
            if key not in instance:
                out.append(f"{path}: missing required key {key!r}")
        for key, value in instance.items():
            if key in props:
                out += errors(value, props[key], f"{path}.{key}")
            elif isinstance(schema.get("additionalProperties"), dict):
                out += errors(value, schema["additionalProperties"], f"{path}.{key}")
            elif schema.get("additionalProperties") is False:
                out.append(f"{path}: unexpected key {key!r}")
    if isinstance(instance, list) and "items" in schema:
        for i, item in enumerate(instance):
            out += errors(item, schema["items"], f"{path}[{i}]")
    return out


def check_schema(schema: dict[str, Any], path: str = "$") -> None:
    """Raise ValueError when any part of ``schema`` uses a keyword outside the subset."""
    unknown = set(schema) - KNOWN
    if unknown:
        raise ValueError(f"{path}: schema keywords outside the subset: {sorted(unknown)}")
    for key, sub in schema.get("properties", {}).items():
        check_schema(sub, f"{path}.{key}")
    for key in ("items", "additionalProperties"):
        if isinstance(schema.get(key), dict):
            check_schema(schema[key], f"{path}.{key}")
