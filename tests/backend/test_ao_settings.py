"""The service's AO settings are AoOptions' (scenesort/ao_options.py): each request field and
query parameter has the definition's default, range, choices and description, a value the
definition refuses is a 422 naming the field and the fix, and the wire layer that reads
the definition imports no engine."""

from __future__ import annotations

import subprocess
import sys

import pytest
from scenesort.backend.wire.models import AoQuery, AoSettings, JobRequest
from scenesort.backend.wire.problems import ApiError

from scenesort.ao_options import AO_OPTIONS, AoOptions

# JSON schema keyword of each end of a range, open and closed
LOW = {False: "minimum", True: "exclusiveMinimum"}
HIGH = {False: "maximum", True: "exclusiveMaximum"}


def _schema_of(name: str, schema: dict) -> dict:
    """The field's schema without its null alternative."""
    kinds = [s for s in schema.get("anyOf", [schema]) if s.get("type") != "null"]
    assert len(kinds) == 1, schema
    return kinds[0]


@pytest.mark.parametrize("model", [JobRequest, AoQuery], ids=lambda m: m.__name__)
def test_every_ao_field_is_the_definitions(model) -> None:
    properties = model.model_json_schema()["properties"]
    names = [n for n in properties if n in AO_OPTIONS]
    assert set(AoSettings.model_fields) <= set(names)
    for name in names:
        spec, schema = AO_OPTIONS[name], properties[name]
        kind = _schema_of(name, schema)
        assert schema.get("default") == spec.default, name
        assert schema["description"] == spec.doc, name
        assert ("anyOf" in schema) == spec.optional, name
        if spec.choices:
            assert tuple(kind["enum"]) == spec.choices, name
        if spec.low is not None:
            assert kind[LOW[spec.low_open]] == spec.low, name
        high = spec.soft_high if spec.soft_high is not None else spec.high
        if high is not None:
            assert kind[HIGH[spec.high_open and spec.soft_high is None]] == high, name


def test_settings_become_the_options_the_engine_takes() -> None:
    query = AoQuery(rays=4, spp=32, target_error=0.05, engine="dacrt")
    assert query.options(threads=2) == AoOptions(spp=32, target_error=0.05, engine="dacrt",
                                                 threads=2)


def test_settings_the_definition_refuses_together_name_the_field_and_the_fix() -> None:
    """Each value is in range, but not together: spp over max_spp with an error target."""
    with pytest.raises(ApiError) as caught:
        AoQuery(rays=1, spp=2000, target_error=0.1).options()
    problem = caught.value
    assert (problem.status, problem.parameter) == (422, "spp")
    assert str(AO_OPTIONS["max_spp"].default) in problem.fix


def test_the_wire_layer_imports_no_engine() -> None:
    """The models read the definition without Warp or the engine (a clean process)."""
    code = ("import sys, scenesort.backend.wire.models, scenesort.backend.wire.binary;"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'warp' "
            "or m.startswith('scenesort.kernels'));"
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
