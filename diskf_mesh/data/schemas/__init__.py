"""JSON Schemas (draft 2020-12) of the JSON formats, shipped as package data.

    diskf-trace-1.json           diskf-trace/1: input of replay, output of simulate
    diskf-estimates-1.json       diskf-estimates/1: output of replay
    diskf-mesh-estimates-1.json  diskf-mesh-estimates/1: world/up --estimates

``check(doc, "diskf-trace/1")`` raises ``InputError`` naming the first
offending field the way the rest of the input checks do (``agents[2].R``,
``y[3][0]``), with a short message of our own instead of jsonschema's (which
repeats the whole offending value). A subschema may carry ``x-field`` (the
field to name) and ``x-message`` (the message) for errors that have no field
of their own, e.g. "A or A_seq is missing". docs/formats.md describes every
field.
"""
from __future__ import annotations

import json
from dataclasses import fields
from functools import cache

import numpy as np
from importlib import resources

from diskf_mesh.core.errors import InputError
from diskf_mesh.estimators import SETTINGS

FILES = {"diskf-trace/1": "diskf-trace-1.json", "diskf-estimates/1": "diskf-estimates-1.json",
         "diskf-mesh-estimates/1": "diskf-mesh-estimates-1.json"}
ROOT_NAMES = {"diskf-trace/1": "trace", "diskf-estimates/1": "estimates", "diskf-mesh-estimates/1": "estimates"}
TYPE_NAMES = {"object": "an object", "array": "a list", "number": "a number", "integer": "an integer",
              "string": "a string", "boolean": "true or false", "null": "null"}


def schema(fmt: str) -> dict:
    """The schema of format ``fmt`` (e.g. ``"diskf-trace/1"``) as a dict.
    A trace's ``estimator`` object also admits the settings of estimator
    plugins (``estimators.SETTINGS`` beyond the file's), by their declaration."""
    out = json.loads(_text(fmt))
    if fmt == "diskf-trace/1":
        known = out["$defs"]["estimator"]["properties"]
        known.update({s.name: setting_schema(s) for s in SETTINGS.values() if s.name not in known})
    return out


def setting_schema(s) -> dict:
    """The JSON Schema of an estimator ``Setting``'s value."""
    if s.table:
        one = {"type": "object", "additionalProperties": False,
               "properties": {f.name: {"type": "boolean"} for f in fields(s.type)}}
    elif s.choices:
        one = {"enum": list(s.choices)}
    else:
        one = {"type": {bool: "boolean", int: "integer", float: "number", str: "string"}[s.type]}
        if s.low is not None:
            one["minimum"] = s.low
    one = {"anyOf": [one, {"type": "null"}]} if s.optional else one
    return {**one, "description": s.doc}


@cache
def _text(fmt: str) -> str:
    return (resources.files(__name__) / FILES[fmt]).read_text()


@cache
def validator(fmt: str):
    """A jsonschema validator of ``fmt`` (imported here: only readers pay for it)."""
    from jsonschema import Draft202012Validator
    from referencing import Registry, Resource

    every = [schema(f) for f in FILES]  # diskf-mesh-estimates/1 refers to diskf-estimates/1
    registry = Registry().with_resources((s["$id"], Resource.from_contents(s)) for s in every)
    s = schema(fmt)
    Draft202012Validator.check_schema(s)
    return Draft202012Validator(s, registry=registry)


def check(doc, fmt: str) -> None:
    """Raise ``InputError(field, message)`` for the best-matching schema
    violation of ``doc`` (jsonschema's ``best_match``), if any."""
    from jsonschema.exceptions import best_match

    error = best_match(validator(fmt).iter_errors(PRUNE.get(fmt, _same)(doc)))
    if error is not None:
        raise InputError(*describe(error, fmt))


# --------------------------------------------------------------------------
# large traces: jsonschema takes about 8 us per value, 15 s for the links and
# measurements of 1,000 agents. Arrays that a quick test shows to conform are
# replaced by a conforming stand-in before validation; any other value is
# validated as it is, so the error message is always jsonschema's finding.
# --------------------------------------------------------------------------
def _same(doc):
    return doc


def _numeric(value, ndims, zero_one=False) -> bool:
    """``value`` is a regular (not ragged), non-empty array of JSON numbers
    (no booleans) with one of ``ndims`` dimensions, entries 0/1 if asked."""
    try:
        a = np.asarray(value)
    except ValueError:  # ragged
        return False
    if a.dtype.kind not in "iuf" or a.ndim not in ndims or a.size == 0:
        return False
    rows = value  # numpy reads true as 1 among numbers: JSON numbers are Python ints and floats only
    for _ in range(a.ndim - 2):
        rows = [r for sub in rows for r in sub]
    return all(type(v) is float or type(v) is int for row in rows for v in row) and (
        not zero_one or bool(np.isin(a, (0, 1)).all()))


def _measurements(y) -> bool:
    """Every entry of every tick is null or a non-empty list of numbers."""
    return isinstance(y, list) and len(y) > 0 and all(
        isinstance(row, list) and all(
            e is None or (type(e) is list and e and all(type(v) in (int, float) for v in e)) for e in row)
        for row in y)


def _prune_trace(doc):
    if not isinstance(doc, dict):
        return doc
    light = dict(doc)
    if _numeric(doc.get("links"), (2, 3), zero_one=True):
        light["links"] = [[1]]
    if _numeric(doc.get("A_seq"), (3,)):
        light["A_seq"] = [[[1.0]]]
    if _measurements(doc.get("y")):
        light["y"] = [[None]]
    truth = doc.get("truth")
    if isinstance(truth, dict):
        light["truth"] = {k: ([[0.0]] if k in ("x", "d") and _numeric(v, (2,)) else v) for k, v in truth.items()}
    return light


PRUNE = {"diskf-trace/1": _prune_trace}


def field_name(path, root: str) -> str:
    """``["agents", 2, "R"]`` -> ``agents[2].R``; the empty path is ``root``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or root


def _json_type(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true or false"
    if isinstance(v, (int, float)):
        return "a number"
    return {str: "a string", list: "a list", dict: "an object"}.get(type(v), type(v).__name__)


def _short(v) -> str:
    text = json.dumps(v)
    return text if len(text) <= 40 else _json_type(v)


def describe(error, fmt: str) -> tuple[str, str]:
    """(field, message) of one jsonschema ``ValidationError`` in a ``fmt`` document."""
    root = ROOT_NAMES[fmt]
    path, kind, value, inst, sch = list(error.absolute_path), error.validator, error.validator_value, \
        error.instance, error.schema
    if "x-message" in sch:
        return sch.get("x-field") or field_name(path, root), sch["x-message"]
    if kind == "required":
        missing = next(k for k in value if k not in inst)
        return field_name(path + [missing], root), "is missing"
    if kind == "additionalProperties":
        extra = sorted(set(inst) - set(sch.get("properties", {})))[0]
        return field_name(path + [extra], root), f"is not a field of {fmt} (see docs/formats.md)"
    field = field_name(path, root)
    if kind == "type":
        types = [value] if isinstance(value, str) else value
        return field, f"must be {' or '.join(TYPE_NAMES[t] for t in types)}, got {_json_type(inst)}"
    if kind in ("anyOf", "oneOf"):
        return field, f"must be {sch.get('description', 'of one of the documented forms')}, got {_short(inst)}"
    if kind == "const":
        return field, f"must be {value!r}, got {_short(inst)}"
    if kind == "enum":
        return field, f"must be one of {', '.join(map(json.dumps, value))}, got {_short(inst)}"
    if kind == "minimum":
        return field, f"must be at least {value}, got {_short(inst)}"
    if kind == "minItems":
        return field, f"must have at least {value} item{'s' if value != 1 else ''}, got {len(inst)}"
    if kind == "uniqueItems":
        return field, "must not repeat an item"
    return field, error.message if len(error.message) <= 120 else f"does not match the schema ({kind})"
