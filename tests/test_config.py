"""Config precedence, validation, plain-data round trip and hashing."""

from __future__ import annotations

import json

import pytest

from sage_core.config import (
    InitMeshConfig,
    config_hash,
    describe,
    from_dict,
    load_config_file,
    resolve_config,
    to_dict,
)
from sage_core.errors import ConfigError, InputError


def test_preset_overrides_defaults():
    default = resolve_config("init-mesh", "default")
    tiny = resolve_config("init-mesh", "tiny")
    assert default.grid.log2_table == 19
    assert tiny.grid.log2_table == 14
    assert tiny.pretrain.steps < default.pretrain.steps


def test_precedence_preset_file_flags(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("init_mesh:\n  mc_resolution: 96\n  pretrain:\n    steps: 50\n    lr_mlp: 0.002\n")
    data = load_config_file(f)
    cfg = resolve_config("init-mesh", "tiny", data, {"pretrain.steps": "70", "bbox_padding": None})
    assert cfg.mc_resolution == 96  # file over preset
    assert cfg.pretrain.steps == 70  # flag over file
    assert cfg.pretrain.lr_mlp == pytest.approx(0.002)
    assert cfg.grid.log2_table == 14  # preset kept where nothing overrides it
    assert cfg.bbox_padding == InitMeshConfig().bbox_padding  # None flag = unset


def test_flat_file_for_single_stage(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"regime": "mv-mf", "height": 200}))
    cfg = resolve_config("ingest", "default", load_config_file(f))
    assert cfg.regime == "mv-mf" and cfg.height == 200


@pytest.mark.parametrize(
    "data,flags,match",
    [
        ({"init_mesh": {"nope": 1}}, {}, "unknown option 'nope'"),
        ({"init_mesh": {}, "bogus_stage": {}}, {}, "unknown section"),
        ({}, {"grid.log2_table": "many"}, "expected an integer"),
        ({}, {"mouth_interior": "perhaps"}, "expected true/false"),
        ({}, {"grid": 3}, "is a section"),
    ],
)
def test_invalid_values_are_errors(data, flags, match):
    with pytest.raises(ConfigError, match=match):
        resolve_config("init-mesh", "default", data, flags)


def test_unknown_preset_and_stage():
    with pytest.raises(ConfigError, match="unknown preset"):
        resolve_config("ingest", "huge")
    with pytest.raises(ConfigError, match="unknown stage"):
        resolve_config("nope", "default")


def test_bad_config_file_names_the_file(tmp_path):
    f = tmp_path / "broken.yaml"
    f.write_text("a: [1, 2\n")
    with pytest.raises(InputError) as e:
        load_config_file(f)
    assert "broken.yaml" in str(e.value)
    with pytest.raises(InputError, match="not found"):
        load_config_file(tmp_path / "missing.yaml")


def test_plain_data_round_trip_and_hash():
    cfg = resolve_config("init-mesh", "tiny")
    d = to_dict(cfg)
    json.dumps(d)  # plain data only
    back = from_dict(InitMeshConfig, d)
    assert back == cfg
    assert config_hash(back) == config_hash(cfg)
    cfg2 = resolve_config("init-mesh", "tiny", None, {"pretrain.steps": 401})
    assert config_hash(cfg2) != config_hash(cfg)


def test_every_field_of_every_stage_is_documented_and_presets_resolve():
    from sage_core.config import PRESETS, STAGE_CONFIGS

    for stage, cls in STAGE_CONFIGS.items():
        for name, help_text, _ in describe(cls):
            assert help_text, f"{stage}: {name} has no help text"
        for preset in PRESETS:
            cfg = resolve_config(stage, preset)
            assert from_dict(cls, to_dict(cfg)) == cfg
