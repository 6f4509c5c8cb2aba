"""Config precedence, validation, plain-data round trip and hashing."""

from __future__ import annotations

import dataclasses
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


def test_tiny_phase1_keeps_the_networks_full_width():
    """The tiny preset shrinks the capture, steps and grids but not the attribute networks: at 32
    units they under-fitted a detailed head (docs/results.md, "Networks at full width")."""
    tiny, default = resolve_config("phase1", "tiny"), resolve_config("phase1", "default")
    assert tiny.appearance.hidden == default.appearance.hidden == 64
    assert tiny.shape.hidden == default.shape.hidden == 64
    assert tiny.appearance.grid_levels < default.appearance.grid_levels


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


def test_a_config_file_that_is_not_utf8_names_the_file(tmp_path):
    from typer.testing import CliRunner

    from sage_cli.app import app

    f = tmp_path / "latin1.yaml"
    f.write_bytes("phase1: {iterations: 5}  # réglages\n".encode("latin-1"))
    with pytest.raises(InputError) as e:
        load_config_file(f)
    assert e.value.path == f and e.value.problem.startswith("cannot read config: not UTF-8 text")
    f.write_bytes(b"\xff\xfe\x00bad")  # a UTF-16 byte-order mark
    res = CliRunner().invoke(app, ["config", "phase1", "--config", str(f)], env={"COLUMNS": "400"})
    assert res.exit_code == 2, res.output
    assert f"{f}: cannot read config: not UTF-8 text" in " ".join(res.output.split())
    f.write_text("phase1: {iterations: 5}  # réglages\n", encoding="utf-8")  # the same text in UTF-8 reads
    assert load_config_file(f) == {"phase1": {"iterations": 5}}


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


# ---- declared choices and ranges ------------------------------------------------------------


def _meta(cls, name):
    import dataclasses

    return next(f.metadata for f in dataclasses.fields(cls) if f.name == name)


def test_every_enum_and_numeric_field_declares_what_it_allows():
    import dataclasses
    import typing

    from sage_core.config import STAGE_CONFIGS

    def walk(cls, prefix=""):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            if dataclasses.is_dataclass(tp):
                yield from walk(tp, f"{prefix}{f.name}.")
            else:
                yield f"{prefix}{f.name}", tp, f.metadata

    for stage, cls in STAGE_CONFIGS.items():
        for name, tp, meta in walk(cls):
            base = [a for a in typing.get_args(tp) if a is not type(None)] or [tp]
            inner = typing.get_origin(base[0]) in (list, tuple) and typing.get_args(base[0])[0] or base[0]
            if inner in (int, float):
                assert {"ge", "gt", "le", "lt", "choices"} & set(meta), f"{stage}: {name} declares no range"
            if inner is str:
                assert "choices" in meta, f"{stage}: {name} declares no choices"


@pytest.mark.parametrize(
    "stage,key,value,allowed",
    [
        ("phase1", "iterations", "-5", ">= 1"),  # int, inclusive lower bound
        ("phase1", "schedule.checkpoint_every", "0", ">= 1"),  # 0 no longer turns checkpoints off silently
        ("phase1", "free.init_opacity", "1", "0 < x < 1"),  # exclusive bounds
        ("phase1", "pseudo.prob", "1.5", "0 <= x <= 1"),  # inclusive bounds
        ("phase1", "near", "0", "> 0"),
        ("phase1", "exposure", "bright", "one of off, gain, rgb"),  # choices
        ("phase1", "render_backend", "cuda", "one of auto, torch, cpp, triton"),
        ("phase2", "teacher", "mesh", "one of rest, neus"),
        ("phase2", "mouth.teeth_color", "0.5,2,0.5", "3 values, each 0 <= x <= 1"),  # list elements
        ("phase2", "wrinkles.quantiles", "0.5", "2 values"),  # list length
        ("init-mesh", "pretrain.steps", "0", ">= 1"),  # nested field: dotted path
        ("init-mesh", "pretrain.truncation", "-0.1", "> 0 or none"[:3]),  # optional float
        ("eval", "split", "train", "one of test, val, all, novel"),
        ("ingest", "regime", "mv", "one of mv-sf, mv-mf, sv-hr, one-shot"),
        ("ingest", "height", "4", ">= 8"),
    ],
)
def test_out_of_range_and_unknown_choices_name_field_value_and_allowed(stage, key, value, allowed):
    with pytest.raises(ConfigError) as e:
        resolve_config(stage, "default", None, {key: value})
    msg = str(e.value)
    assert f"{stage} config: {key} = " in msg and allowed in msg, msg


def test_validation_sees_every_source_and_accepts_bounds_and_none(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("phase1:\n  iterations: 0\n")
    with pytest.raises(ConfigError, match="iterations = 0"):
        resolve_config("phase1", "tiny", load_config_file(f))
    # a flag repairs what the file broke: validation runs once, on the merged config
    assert resolve_config("phase1", "tiny", load_config_file(f), {"iterations": 3}).iterations == 3
    cfg = resolve_config("phase1", "default", None, {"pseudo.prob": 1, "free.sh_degree": 3, "schedule.rebind_every": 0})
    assert cfg.pseudo.prob == 1.0 and cfg.free.sh_degree == 3 and cfg.schedule.rebind_every == 0
    assert resolve_config("init-mesh", "default", None, {"pretrain.truncation": "none"}).pretrain.truncation is None


def test_allowed_values_are_described_and_match_the_engine():
    from sage_core.avatar.shading import SHADING_MODES
    from sage_core.avatar.surfels import ATTRIBUTE_MODES
    from sage_core.config import EvalConfig, Phase1Config, Phase2Config, describe_allowed
    from sage_core.data.ingest import REGIMES
    from sage_core.render import BACKENDS
    from sage_core.train.phase2 import TEACHERS

    assert set(_meta(Phase1Config, "shading")["choices"]) == set(SHADING_MODES)
    assert set(_meta(Phase1Config, "attributes")["choices"]) == set(ATTRIBUTE_MODES)
    assert set(_meta(Phase2Config, "teacher")["choices"]) == set(TEACHERS)
    assert set(_meta(Phase1Config, "render_backend")["choices"]) == set(BACKENDS)
    from sage_core.config import IngestConfig

    assert set(_meta(IngestConfig, "regime")["choices"]) == set(REGIMES)
    allowed = describe_allowed(InitMeshConfig)
    assert allowed["pretrain.steps"] == ">= 1" and allowed["pretrain.truncation"] == "> 0 or none"
    assert describe_allowed(EvalConfig)["split"] == "one of test, val, all, novel"


def test_presets_are_declared_in_one_table():
    import inspect

    import sage_core.config as config

    import re

    src = inspect.getsource(config)
    assert not re.search(r"^(PRESET_OVERRIDES|STAGE_CONFIGS)(\[[^\]]*\])+\s*=|^(PRESET_OVERRIDES|STAGE_CONFIGS)\S*\.update\(", src, re.M)
    assert set(config.PRESET_OVERRIDES["tiny"]) == set(config.STAGE_CONFIGS)
    assert resolve_config("phase2", "tiny").iterations == 300


@pytest.mark.parametrize(
    "stage,flags,match",
    [
        ("ingest", {"height": 100, "downsample": 2}, r"either height or downsample.*height = 100, downsample = 2.0"),
        ("init-mesh", {"grid.base_res": 4096}, r"base_res must not exceed max_res.*grid.base_res = 4096, grid.max_res = 2048"),
        ("phase1", {"near": 5}, r"near must be smaller than far.*near = 5.0, far = 3.0"),
        ("phase2", {"wrinkles.quantiles": "0.9,0.5"}, r"first quantile must be below the second.*wrinkles.quantiles = \[0.9, 0.5\]"),
        ("phase1", {"densify": "true"}, r"density control needs free surfel attributes.*densify.enabled = True, attributes = 'mlp'"),
    ],
)
def test_rules_across_fields(stage, flags, match):
    with pytest.raises(ConfigError, match=match):
        resolve_config(stage, "default", None, flags)


# ---- the sections of the phase configs and their legacy flat names -------------------------------


def test_phase_configs_share_their_neus_loss_and_schedule_sections():
    from sage_core.config import LossWeights, NeuSConfig, Phase1Config, Phase2Config, Schedule

    p1, p2 = Phase1Config(), Phase2Config()
    assert isinstance(p1.neus, NeuSConfig) and type(p2.neus) is NeuSConfig
    assert isinstance(p1.loss, LossWeights) and isinstance(p2.loss, LossWeights)
    assert isinstance(p1.schedule, Schedule) and isinstance(p2.schedule, Schedule)
    # one declaration, each phase with its own defaults
    assert p1.schedule.checkpoint_every == 1000 and p2.schedule.checkpoint_every == 500
    # the listing shows the phase's own defaults
    assert {n: d for n, _, d in describe(Phase2Config)}["schedule.checkpoint_every"] == 500


@pytest.mark.parametrize("stage", ["phase1", "phase2"])
def test_every_legacy_flat_key_is_accepted_and_sets_its_field(stage):
    """The flat key names of the earlier flat configs (the canonical form's keys) keep working in
    flags, files and saved configs; a changed value lands in the nested field."""
    from sage_core.config import STAGE_CONFIGS, canonical_form, get_field, legacy_aliases

    cls = STAGE_CONFIGS[stage]
    aliases = legacy_aliases(cls)
    flat = canonical_form(cls())
    # fields added later stay out of the canonical form at their default: the top-level ones and
    # those with a flat name (a section whose other fields have flat names gives its new ones one too)
    def is_added(name: str) -> bool:
        obj: object = cls()
        *sections, last = name.split(".")
        for sec in sections:
            obj = getattr(obj, sec)
        return bool({f.name: f for f in dataclasses.fields(obj)}[last].metadata.get("added"))

    added = {n for n, _, _ in describe(cls) if is_added(n)}
    top = {a for a, n in aliases.items() if n not in added} | {n for n, _, _ in describe(cls) if "." not in n and n not in added}
    # sections given fields after the nesting (phase 1's relocate) appear under their own name
    later = {n.split(".")[0] for n, _, _ in describe(cls) if "." in n and n not in aliases.values()}
    assert top <= set(flat) and set(flat) - top <= later, set(flat) - top
    assert all(n in aliases or "." not in n for n in flat)
    # an old saved config (plain flat data) rebuilds the same config
    assert from_dict(cls, flat) == cls()
    # each legacy key, given a value that differs from the default, sets the nested field
    for old, new in aliases.items():
        default = get_field(cls(), new)
        if isinstance(default, bool):
            value = not default
        elif isinstance(default, str) or default is None:
            continue
        elif isinstance(default, list):
            value = list(reversed(default)) if len(default) != 2 else [0.1, 0.2]
        else:
            value = default + 1 if isinstance(default, int) else default / 2 + 0.01
        cfg = cls()
        from sage_core.config import _apply

        _apply(cfg, old, value, "test")
        assert get_field(cfg, new) == value, (old, new)


def test_legacy_keys_in_files_flags_and_sections(tmp_path):
    f = tmp_path / "old.yaml"
    f.write_text("phase1:\n  w_light_albedo: 2\n  n_surfels: 5000\n  pseudo_view_prob: 0.25\nphase2:\n  correction_mode: curvature\n"
                 "  wrinkle_shading: false\n  teacher_max_views: 8\n")  # fmt: skip
    p1 = resolve_config("phase1", "tiny", load_config_file(f), {"w_pt": "0.5", "schedule.sdf_from": 7})
    assert p1.loss.light_albedo == 2.0 and p1.surfels.count == 5000 and p1.pseudo.prob == 0.25 and p1.loss.pt == 0.5
    assert p1.schedule.sdf_from == 7
    p2 = resolve_config("phase2", "tiny", load_config_file(f), {"correction": "off"})
    assert p2.correction.mode == "curvature" and p2.wrinkles.enabled is False and p2.rest_teacher.max_views == 8
    assert p2.correction.enabled is False
    # a legacy name that is also a section: a mapping addresses the section, a plain value its switch
    on = resolve_config("phase1", "default", None, {"attributes": "free", "densify": "true", "densify_every": 7})
    assert on.densify.enabled and on.densify.every == 7
    nested = resolve_config("phase1", "default", {"phase1": {"attributes": "free", "densify": {"enabled": True, "every": 7}}})
    assert nested == on
    assert resolve_config("phase2", "default", None, {"unseen_fill": "true"}).unseen_fill.enabled is True
    # a new config file, nested
    g = tmp_path / "new.yaml"
    g.write_text("phase1:\n  loss:\n    light_albedo: 2\n  surfels:\n    count: 5000\n")
    assert resolve_config("phase1", "tiny", load_config_file(g)).loss.light_albedo == 2.0
    with pytest.raises(ConfigError, match="unknown option 'loss.nope'"):
        resolve_config("phase1", "tiny", None, {"loss.nope": 1})
    # an error on a legacy key names the field it set
    with pytest.raises(ConfigError, match=r"phase1 config: loss.pt = -1.0 is out of range"):
        resolve_config("phase1", "tiny", None, {"w_pt": -1})


def test_the_hash_of_a_config_does_not_depend_on_the_names_it_was_given_with():
    a = resolve_config("phase1", "tiny", None, {"w_light_albedo": 2, "n_surfels": 5000})
    b = resolve_config("phase1", "tiny", None, {"loss.light_albedo": 2, "surfels.count": 5000})
    assert a == b and config_hash(a) == config_hash(b) != config_hash(resolve_config("phase1", "tiny"))
    # a saved nested config round-trips with its hash
    assert config_hash(from_dict(type(a), to_dict(a))) == config_hash(a)


@pytest.mark.parametrize(
    "value,expected",
    [("500", 500), (500, 500), ("1e4", 10000), (1e4, 10000), ("2.0", 2), ("1_000", 1000)],
)
def test_integer_fields_take_whole_numbers_in_any_spelling(value, expected):
    assert resolve_config("phase1", "tiny", None, {"iterations": value}).iterations == expected


@pytest.mark.parametrize(
    "value,match",
    [
        ("1e23", r"iterations: '1e23' is too large for an integer setting"),  # was logged as 99999999999999991611392
        (1e23, r"too large for an integer setting"),
        ("1e10", r"iterations = 10000000000 is out of range \(allowed: at most 2147483647\)"),
        ("1.5", "expected an integer"),
        ("nan", "expected an integer"),
        ("inf", "expected an integer"),
        (True, "expected an integer"),
    ],
)
def test_integer_fields_refuse_fractions_and_absurd_magnitudes(value, match):
    with pytest.raises(ConfigError, match=match):
        resolve_config("phase1", "tiny", None, {"iterations": value})


def test_integer_cap_applies_to_every_integer_field_without_a_bound(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"phase2": {"expressions": {"active": 3e9}}}))
    with pytest.raises(ConfigError, match=r"expressions.active = 3000000000 is out of range"):
        resolve_config("phase2", "tiny", load_config_file(f))
    # a declared bound still wins, and the large values the suite uses stay valid
    assert resolve_config("phase1", "tiny", None, {"sdf_from": 1_000_000_000}).schedule.sdf_from == 1_000_000_000


def test_regimes_take_the_synth_spellings_too(tmp_path):
    from sage_cli.commands.synth import INGEST_SPELLINGS
    from sage_core.batch import load_subjects
    from sage_core.config import REGIMES, canonical_regime
    from sage_core.data.synthetic import REGIMES as SYNTH_REGIMES

    assert resolve_config("ingest", flags={"regime": "oneshot"}).regime == "one-shot"
    assert resolve_config("ingest", flags={"regime": "monocular"}).regime == "sv-hr"
    assert resolve_config("ingest", flags={"regime": "MV-SF"}).regime == "mv-sf"
    with pytest.raises(ConfigError, match="regime = 'multiview' is not allowed"):
        resolve_config("ingest", flags={"regime": "multiview"})  # one or all timesteps? mv-sf or mv-mf
    assert {canonical_regime(r) for r in REGIMES} == set(REGIMES)
    assert set(INGEST_SPELLINGS) >= {"one-shot", "sv-hr"} and set(INGEST_SPELLINGS.values()) <= set(SYNTH_REGIMES)
    (tmp_path / "cap").mkdir()
    (tmp_path / "s.csv").write_text("id,capture,regime\na,cap,oneshot\nb,cap,monocular\n")
    assert [s.regime for s in load_subjects(tmp_path / "s.csv")] == ["one-shot", "sv-hr"]


def test_one_flag_parser_for_stage_track_and_synth_configs():
    """Stage configs, `sage track` and `sage synth` read true/false alike (one parser)."""
    from sage_core.config import parse_bool
    from sage_core.data.synthetic.config import parse_sets
    from sage_core.track.config import resolve_track_config

    assert [parse_bool(v) for v in (True, 1, " Yes ", "on", "TRUE")] == [True] * 5
    assert [parse_bool(v) for v in (False, 0, "no", " off", "False")] == [False] * 5
    for bad in ("maybe", 2, "", None):
        with pytest.raises(ValueError):
            parse_bool(bad)
    assert resolve_track_config("default", None, {"steady_depth": "yes"}).steady_depth is True
    assert resolve_track_config("default", None, {}).steady_pivot == "auto"
    assert [resolve_track_config("default", None, {"steady_pivot": v}).steady_pivot for v in ("on", "true", True, "no", "auto")] \
        == ["on", "on", "on", "off", "auto"]
    with pytest.raises(ConfigError, match="steady_pivot"):
        resolve_track_config("default", None, {"steady_pivot": "sometimes"})
    assert parse_sets(["novel_multiview=off"]) == {"novel_multiview": False}
    with pytest.raises(ConfigError, match="steady_depth"):
        resolve_track_config("default", None, {"steady_depth": "maybe"})
    with pytest.raises(ConfigError, match="true or false"):
        parse_sets(["novel_multiview=maybe"])


def test_every_regimes_stage_configs_hash_and_the_single_camera_ones_cover_the_unseen_neck():
    """Each regime's defaults hash (a field added to a section with flat names takes its own flat
    name, never clashing with the section's) and set what the regime needs."""
    from sage_core.config import REGIMES, canonical_form

    hashes = {}
    for regime in REGIMES:
        for stage in ("phase1", "phase2"):
            cfg = resolve_config(stage, "tiny", regime=regime)
            hashes[(regime, stage)] = config_hash(cfg)
            assert from_dict(type(cfg), canonical_form(cfg)) == cfg
        p2 = resolve_config("phase2", "tiny", regime=regime)
        single = regime in ("sv-hr", "one-shot")
        assert p2.unseen_fill.enabled == p2.unseen_fill.cover_neck == p2.unseen_fill.cover_away == single
        assert canonical_form(p2).get("unseen_fill_cover_neck", False) == single
        assert canonical_form(p2).get("unseen_fill_cover_away", False) == single
        # a head-turn clip's avatar spreads its surfels over the hair by area like the ears, and gives
        # the triangles its cameras face less extra density (they face all of the head but its back)
        layout = resolve_config("phase1", "tiny", regime=regime).surfels
        clip = regime == "sv-hr"
        assert (layout.hair_weight, layout.camera_weight) == ((1.0, 1.0) if clip else (0.5, 2.0))
    assert hashes[("one-shot", "phase2")] != hashes[("mv-sf", "phase2")]
