"""Typed method parameters: the names, types and ranges a launch file, ``--set`` and
``olsplat aggregate|eval`` are held to, and the store manifest that pins them for a run."""

from __future__ import annotations

import json

import pytest

from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.method import METHODS, Method, MethodParams, claim_store, read_manifest
from olsplat_nodes.params import ParameterError, parse_assignments, parse_params


def test_unset_fields_keep_the_named_methods_values():
    assert MethodParams().resolve() == METHODS["outlangsplat"]
    projection = MethodParams(method="projection", tau_d=0.2).resolve()
    assert projection.raster == METHODS["projection"].raster  # its 32-wide Top-K stays
    assert projection.aggregation.tau_d == 0.2 and projection.aggregation.use_quality is False


def test_values_are_converted_as_yaml_gives_them():
    settings = parse_assignments(["tau_d=0.3", "beta=[1, 2, 4]", "iterations=2", "topk_max=24"], "--set")
    method = parse_params(MethodParams, settings, "--set").resolve()
    assert method.aggregation.tau_d == 0.3 and method.aggregation.beta == (1.0, 2.0, 4.0)
    assert method.aggregation.iterations == 2 and method.raster.topk_max == 24
    gate_off = MethodParams(min_retained_views=0.0, level_weights=()).resolve()
    assert gate_off.aggregation.min_retained_views is None and gate_off.aggregation.level_weights is None


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ({"tau_dd": 0.3}, "where: unknown parameter 'tau_dd'; did you mean tau_d"),
        ({"tau_d": "0.3"}, "where.tau_d: expected a number or null, got '0.3'"),
        ({"iterations": 2.5}, "where.iterations: expected an integer or null, got 2.5"),
        ({"iterations": True}, "where.iterations: expected an integer or null, got True"),
        ({"beta": "1,2"}, "where.beta: expected a list of numbers or null, got '1,2'"),
        ({"tau_d": float("nan")}, "where.tau_d: expected a number or null, got nan"),
    ],
)
def test_wrong_names_and_types_are_named(raw, message):
    with pytest.raises(ParameterError) as caught:
        parse_params(MethodParams, raw, "where")
    assert str(caught.value).startswith(message)


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (MethodParams(method="nope"), "where.method: unknown method 'nope'; known: outlangsplat"),
        (MethodParams(q_min=0.0), "where: q_min must be in (0, 1]"),
        (MethodParams(topk_min=40), "where: need 1 <= topk_min <= topk_max"),
    ],
)
def test_out_of_range_values_are_named(params, message):
    with pytest.raises(ParameterError) as caught:
        params.resolve("where")
    assert str(caught.value).startswith(message)


def test_every_method_round_trips_through_its_record():
    for method in METHODS.values():
        assert Method.from_record(json.loads(json.dumps(method.record())), "record") == method


def test_a_store_keeps_its_settings_and_refuses_others(tmp_path):
    store = tmp_path / "store"
    assert read_manifest(store) is None
    chosen = MethodParams(tau_d=0.3).resolve()
    assert claim_store(store, chosen).method == chosen
    assert read_manifest(store).method.aggregation.tau_d == 0.3
    assert claim_store(store, chosen).method == chosen  # a restart with the same settings resumes
    with pytest.raises(
        OlsplatInputError,
        match=r"manifest.json: this store was made with other method settings \(tau_d: 0.3 in the store, 0.05 now\)",
    ):
        claim_store(store, MethodParams().resolve())
    fused = tmp_path / "fused"  # the 3D branch's settings are part of what a store was made with
    structure = {"lambda_f": 0.7, "tau_o": 0.1, "voxel": None, "minkunet": None}
    assert claim_store(fused, chosen, structure).structure == structure
    assert read_manifest(fused).structure == structure
    with pytest.raises(OlsplatInputError, match=r"features: '2d3d' in the store, '2d' now"):
        claim_store(fused, chosen)
    with pytest.raises(OlsplatInputError, match=r"3d.lambda_f: 0.7 in the store, 0.5 now"):
        claim_store(fused, chosen, {**structure, "lambda_f": 0.5})
    (store / "manifest.json").write_text("{not json")
    with pytest.raises(OlsplatInputError, match=r"manifest.json: unreadable store manifest"):
        read_manifest(store)


def test_the_accumulator_takes_the_shipped_minkunet_and_names_a_missing_one(tmp_path):
    from olsplat_nodes.nodes.accumulator import AccumulatorNode
    from olsplat_nodes.structure.branch import SHIPPED_MINKUNET

    shipped = AccumulatorNode.Params(store=str(tmp_path / "a"), features="2d3d", minkunet="shipped")
    AccumulatorNode.validate(shipped, "accumulator")
    assert AccumulatorNode._structure(shipped).minkunet == SHIPPED_MINKUNET and SHIPPED_MINKUNET.is_file()
    missing = AccumulatorNode.Params(store=str(tmp_path / "b"), features="2d3d", minkunet=str(tmp_path / "no.pt"))
    with pytest.raises(ParameterError, match=r"accumulator\.minkunet: .*no\.pt: no such MinkUNet checkpoint"):
        AccumulatorNode.validate(missing, "accumulator")


def test_a_number_in_exponent_form_is_a_number_as_yaml_1_2_reads_it():
    """``--set`` values and launch files: ``1e9`` and ``2E-3`` are floats (PyYAML alone keeps
    them strings); a quoted one and text that only looks like one stay strings."""
    settings = parse_assignments(["a=1e9", "b=-2E-3", "c=1.5e+2", "d='1e9'", "e=1e", "f=e9", "g=3"], "--set")
    assert settings == {"a": 1e9, "b": -2e-3, "c": 150.0, "d": "1e9", "e": "1e", "f": "e9", "g": 3}
    assert isinstance(settings["g"], int)
