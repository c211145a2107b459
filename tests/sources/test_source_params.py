"""The source parameters are typed, and their telemetry_* part is TelemetryConfig's fields
exactly (same names, same defaults): the two cannot drift apart."""

from dataclasses import fields

import pytest

from olsplat_nodes.params import ParameterError
from olsplat_nodes.sources import SourceParams, open_source
from olsplat_nodes.telemetry import TelemetryConfig


def test_telemetry_params_are_telemetry_configs_fields():
    telemetry = {
        f.name.removeprefix("telemetry_"): f.default for f in fields(SourceParams) if f.name.startswith("telemetry_")
    }
    assert telemetry == {f.name: f.default for f in fields(TelemetryConfig)}


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"rate_hz": "fast"}, "source.rate_hz: expected a number, got 'fast'"),
        ({"fixed_pose": "1 0 0"}, "source.fixed_pose: expected a list of numbers, got '1 0 0'"),
        ({"telemetry_reference": [1, 2]}, "source.telemetry_reference: expected a list of 3 numbers or null"),
        ({"sauce": "x"}, "source: unknown parameter 'sauce'; did you mean source?"),
    ],
)
def test_bad_source_params_are_named(spec, message):
    with pytest.raises(ParameterError) as caught:
        open_source(spec)
    assert str(caught.value).startswith(message)
