"""Each stage config declares its rules beside its fields: every non-boolean field has one, every rule and
relation names a field that exists, and stage 1's pair-cache key follows the fields' declarations."""

from __future__ import annotations

import dataclasses

import pytest

from taichi_gs.errors import InputError
from taichi_gs.stages.declaration import STAGE_NAMES, declared
from taichi_gs.validation import (
    LEARNING_RATE,
    METADATA_KEYS,
    Rule,
    rules_of,
    setting,
    validate_sections,
)

CONFIGS = {name: declared(name).config_type for name in STAGE_NAMES}


@pytest.mark.parametrize("stage", STAGE_NAMES)
def test_every_non_boolean_field_declares_its_rules(stage):
    fields = dataclasses.fields(CONFIGS[stage])
    missing = [f.name for f in fields if f.type != "bool" and not rules_of(f)]
    assert not missing, f"[{stage}] fields without a rule (declare one with setting(default, RULE)): {missing}"
    for f in fields:
        assert set(f.metadata) <= METADATA_KEYS, (f.name, set(f.metadata))
        assert all(isinstance(rule, Rule) for rule in rules_of(f)), f.name
        assert not f.name.startswith("lr_") or rules_of(f)[0] is LEARNING_RATE, f.name


@pytest.mark.parametrize("stage", STAGE_NAMES)
def test_every_relation_names_fields_that_exist(stage):
    config = CONFIGS[stage]
    names = {f.name for f in dataclasses.fields(config)}
    for text, check in getattr(config, "RELATIONS", ()):
        assert set(check.__code__.co_names) - {"len"} <= names, text
        for preset in declared(stage).presets.values():
            assert check(preset), text


def test_unknown_field_metadata_is_refused():
    with pytest.raises(TypeError, match="unknown config field metadata"):
        setting(1.0, paired=False)


def test_a_broken_rule_names_the_key_and_the_rule():
    presets = {name: declared(name).presets["fast"] for name in STAGE_NAMES}
    broken = {**presets, "deblur": dataclasses.replace(presets["deblur"], lr_exposure=2.0)}
    with pytest.raises(InputError, match=r"\[deblur\] lr_exposure = 2 is not a learning rate in \[0, 1\]"):
        validate_sections(broken)
    broken = {**presets, "deblur": dataclasses.replace(presets["deblur"], lr_test_pose=0.0)}
    with pytest.raises(InputError, match=r"\[deblur\] lr_test_pose = 0.0 must be above 0"):
        validate_sections(broken)
    broken = {**presets, "deblur": dataclasses.replace(presets["deblur"], densify_from=400, densify_until=300)}
    with pytest.raises(InputError, match=r"\[deblur\] densify_from must not exceed densify_until"):
        validate_sections(broken)


def _other(value):
    """A valid-looking different value of the same type."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value * 2 + 1
    if isinstance(value, tuple):
        return value + value[-1:]
    return value + "x"


def test_the_pair_cache_key_changes_with_the_fields_declared_to_change_a_pair():
    """Stage 1's pair cache is keyed by every field but those declared ``pair=False`` (the graph's, the
    fused cloud's, the readout's, the threads)."""
    from taichi_gs.stages.pose_config import PRESETS

    base = PRESETS["fast"]
    outside = []
    for f in dataclasses.fields(base):
        changed = dataclasses.replace(base, **{f.name: _other(getattr(base, f.name))})
        if changed.pair_key() == base.pair_key():
            outside.append(f.name)
    declared_outside = [f.name for f in dataclasses.fields(base) if f.metadata.get("pair") is False]
    assert outside == declared_outside
    assert {"voxel_size_m", "pose_graph", "threads", "readout_ms"} <= set(outside)
    assert "flow_preset" not in outside
