"""What the OpenAPI document must tell a client generated from it (test_generated_client.py runs one): the bearer
scheme on every owner's operation, readable unique operation ids, the choices as named enums, and the files that go
up and come down."""
from __future__ import annotations

import re
from typing import get_args

from drop_engine.config import Algorithm, Preset
from drop_engine.envs import EnvName
from drop_engine.formats import Format
from kernel.job_state import JobStatus


def _operations(spec: dict):
    for path, methods in spec["paths"].items():
        for method, operation in methods.items():
            yield method.upper(), path, operation


def test_every_owners_operation_declares_the_bearer_scheme(app):
    spec = app.openapi()
    scheme = spec["components"]["securitySchemes"]["bearer"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    for method, path, operation in _operations(spec):
        expected = [{"bearer": []}] if path.startswith("/v1/") else None
        assert operation.get("security") == expected, (method, path)


def test_operation_ids_are_readable_and_unique(app):
    ids = {(method, path): op["operationId"] for method, path, op in _operations(app.openapi())}
    assert len(set(ids.values())) == len(ids)
    assert all(re.fullmatch(r"(datasets|jobs|health)(-[a-z]+)+", op_id) for op_id in ids.values()), ids
    assert ids["POST", "/v1/datasets"] == "datasets-upload"
    assert ids["GET", "/v1/jobs/{job_id}/policy"] == "jobs-get-policy"


def test_choices_are_named_enums(app):
    spec = app.openapi()
    schemas = spec["components"]["schemas"]
    for name, values in (("Algorithm", get_args(Algorithm)), ("Preset", get_args(Preset)),
                         ("EnvName", get_args(EnvName)), ("DatasetFormat", get_args(Format)),
                         ("JobStatus", [s.value for s in JobStatus])):
        assert schemas[name]["enum"] == list(values), name
    ref = "#/components/schemas/{}".format
    request, job = schemas["JobRequest"]["properties"], schemas["JobOut"]["properties"]
    assert request["algorithm"]["$ref"] == job["algorithm"]["$ref"] == ref("Algorithm")
    assert request["preset"]["$ref"] == job["preset"]["$ref"] == ref("Preset")
    assert {"$ref": ref("EnvName")} in request["env"]["anyOf"] and job["env"]["$ref"] == ref("EnvName")
    assert job["status"]["$ref"] == ref("JobStatus")
    status = next(p for p in spec["paths"]["/v1/jobs"]["get"]["parameters"] if p["name"] == "status")
    assert {"$ref": ref("JobStatus")} in status["schema"]["anyOf"]


def test_files_are_declared(app):
    paths = app.openapi()["paths"]
    binary = {"schema": {"type": "string", "format": "binary"}}
    upload = paths["/v1/datasets"]["post"]["requestBody"]
    assert upload["required"] and upload["content"]["application/octet-stream"] == binary
    form = upload["content"]["multipart/form-data"]["schema"]
    assert form["required"] == ["file"] and form["properties"]["file"].items() >= binary["schema"].items()
    policy = paths["/v1/jobs/{job_id}/policy"]["get"]["responses"]["200"]["content"]
    assert policy["application/octet-stream"] == binary
    assert policy["application/json"]["schema"]["$ref"] == "#/components/schemas/PolicyMetadata"
    assert paths["/v1/jobs/{job_id}/curve.png"]["get"]["responses"]["200"]["content"] == {"image/png": binary}
