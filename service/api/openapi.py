"""What the OpenAPI page says about uploads and methods, made exact.

* ``stacks`` carry ``minItems: 1`` and ``maxItems: SVRNET_MAX_FILES``, ``masks`` ``maxItems`` too: a
  generated client never sends a list the schema calls valid and the server refuses;
* optional form fields, headers and query parameters are optional, not nullable (a multipart form
  or a header cannot send a null: FastAPI's ``anyOf [..., null]`` made generated clients send the
  text ``null``);
* a form field's text is never empty (``minLength: 1``): an empty value is refused (400), as FastAPI
  would read it as absent and take the default;
* ``poses`` (read by ``POST /v1/reconstructions`` from the raw form: a JSON text or a JSON file) is
  documented with the other fields;
* :func:`allowed_methods` lists every documented method of a path, for ``Allow`` (on ``405`` and
  ``OPTIONS``): Starlette's own answer names only the methods of the first route that matched;
* where ``SVRNET_API_KEYS`` is set, the operations that need a key say so (``security``: a bearer
  token or ``X-API-Key``, :data:`KEY_SCHEMES`), so the page's "Authorize" sends it; a server without
  keys declares none.
"""

from __future__ import annotations

from collections.abc import Callable

from fastapi import FastAPI

POSES = {
    "anyOf": [{"type": "string", "format": "binary"}, {"type": "string", "minLength": 1}],
    "title": "Poses",
    "description": "optional: the JSON body /v1/predict returned for the same files (as a JSON file or text); "
                   "without it the job predicts the poses first",
}
EXTRA_FIELDS = {"/v1/reconstructions": {"poses": POSES}}
KEY_SCHEMES = {
    "bearer": {"type": "http", "scheme": "bearer", "description": "a key of SVRNET_API_KEYS"},
    "apiKey": {"type": "apiKey", "in": "header", "name": "X-API-Key", "description": "a key of SVRNET_API_KEYS"},
}
"""The two ways a request presents its API key (either one)."""


def document_uploads(app: FastAPI, max_files: int, needs_key: Callable[[str], bool] | None = None) -> None:
    """Add the list sizes and the undeclared ``poses`` field to the multipart bodies of ``app``'s schema;
    with ``needs_key`` (where keys are configured: whether a path needs one), the key schemes."""
    generate = app.openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        schema = generate()
        components = schema.get("components", {}).get("schemas", {})
        for path, ops in schema.get("paths", {}).items():
            for op in ops.values():
                for param in op.get("parameters", []):           # a header or query value is given or not: never null
                    param["schema"] = _not_null(param.get("schema", {}))
                body = op.get("requestBody", {}).get("content", {}).get("multipart/form-data", {}).get("schema", {})
                target = components.get(body.get("$ref", "").rsplit("/", 1)[-1])
                if target is None:
                    continue
                props = target.setdefault("properties", {})
                target["additionalProperties"] = False         # unknown fields are refused (400)
                for name, prop in props.items():     # a form field is given or left out: never null, never empty
                    props[name] = _not_empty(_not_null(prop))
                for name, low in (("stacks", 1), ("masks", 0)):
                    if props.get(name, {}).get("type") == "array":
                        props[name]["maxItems"] = max_files
                        if low:
                            props[name]["minItems"] = low
                props.update(EXTRA_FIELDS.get(path, {}))
        if needs_key is not None:
            schema.setdefault("components", {})["securitySchemes"] = KEY_SCHEMES
            for path, ops in schema.get("paths", {}).items():
                for op in ops.values():
                    if needs_key(path):
                        op["security"] = [{name: []} for name in KEY_SCHEMES]
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _not_null(prop: dict) -> dict:
    """``prop`` without the ``null`` of FastAPI's ``anyOf [X, null]`` for an optional value: ``X`` with
    ``prop``'s other keys (its title, description and constraints).

    Example:
        >>> _not_null({"anyOf": [{"type": "string"}, {"type": "null"}], "minLength": 8})
        {'minLength': 8, 'type': 'string'}
    """
    variants = [v for v in prop.get("anyOf", []) if v.get("type") != "null"]
    if "anyOf" in prop and len(variants) == 1:
        return {**{k: v for k, v in prop.items() if k != "anyOf"}, **variants[0]}
    return prop


def _not_empty(prop: dict) -> dict:
    """``prop`` with ``minLength: 1`` on its text (not a file), its list's items' or its variants'.

    Example:
        >>> _not_empty({"type": "array", "items": {"type": "string"}})
        {'type': 'array', 'items': {'type': 'string', 'minLength': 1}}
        >>> _not_empty({"type": "string", "format": "binary"})
        {'type': 'string', 'format': 'binary'}
    """
    if prop.get("type") == "string" and prop.get("format") != "binary":
        return {**prop, "minLength": max(1, prop.get("minLength", 1))}
    if prop.get("type") == "array" and isinstance(prop.get("items"), dict):
        return {**prop, "items": _not_empty(prop["items"])}
    if "anyOf" in prop:
        return {**prop, "anyOf": [_not_empty(v) for v in prop["anyOf"]]}
    return prop


def allowed_methods(app: FastAPI, path: str) -> list[str]:
    """The methods the OpenAPI schema documents for ``path`` (HEAD with GET, and OPTIONS), for ``Allow``;
    empty when no documented path matches."""
    parts = path.rstrip("/").split("/")
    methods: set[str] = set()
    for template, ops in app.openapi().get("paths", {}).items():
        tparts = template.rstrip("/").split("/")
        if len(tparts) == len(parts) and all(t == p or (t.startswith("{") and p) for t, p in zip(tparts, parts)):
            methods |= {m.upper() for m in ops}
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods | {"OPTIONS"}) if methods else []


__all__ = ["allowed_methods", "document_uploads"]
