"""The one list of field kinds (runtime.fields.field_kinds) and what follows it: the torch twins
(train.scene.field_kinds), the JavaScript registry (web/src/fields/index.js), the fit presets and the command
line's choices (train.scene.presets); and the kind base class's defaults."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from noisenerf.cli.main import build_parser
from noisenerf.runtime.fields import FieldKind, field_kinds
from noisenerf.train.scene.presets import DEFAULT_FIELDS, DEFAULT_PRESETS, PRESET_KINDS

WEB = Path(__file__).resolve().parents[1] / "web"


def test_the_torch_twins_are_the_registered_kinds_in_order():
    from noisenerf.train.scene.field_kinds import CLASSES

    assert list(CLASSES) == list(field_kinds()) == ["mlp", "hashgrid", "nerfacto"]


def test_the_javascript_registry_is_the_pythons():
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the browser reveal's registry needs Node 20 (CI installs it)")
    script = ("import { fieldKinds } from './src/fields/index.js';"
              "const kinds = fieldKinds();"
              "console.log(JSON.stringify(Object.values(kinds).map((k) => [k.name, k.opset, k.proposalSampler({}) === null])));")
    result = subprocess.run(["node", "--input-type=module", "-e", script], cwd=WEB, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    python = [[kind.name, kind.opset, type(kind).proposal_sampler is FieldKind.proposal_sampler]
              for kind in field_kinds().values()]
    assert json.loads(result.stdout) == python


def test_every_kind_is_a_field_kind_and_keeps_the_defaults_it_does_not_override():
    kinds = field_kinds()
    assert all(isinstance(kind, FieldKind) and kind.name == name for name, kind in kinds.items())
    # a kind rendered with the scene's own sampling says nothing of proposals: the base class answers None
    assert [name for name, kind in kinds.items() if "proposal_sampler" in vars(type(kind))] == ["nerfacto"]
    assert kinds["mlp"].proposal_sampler({}) is None


def test_the_presets_are_fits_and_the_command_lines_choices():
    from noisenerf.train.scene.fit import PRESETS

    assert {name: config.field.kind for name, config in PRESETS.items()} == PRESET_KINDS
    assert set(PRESET_KINDS.values()) <= set(field_kinds()) and set(DEFAULT_FIELDS.values()) <= set(DEFAULT_PRESETS)
    assert all(PRESET_KINDS[preset] == kind for kind, preset in DEFAULT_PRESETS.items())
    fit = build_parser()._subparsers._group_actions[0].choices["fit"]
    choices = {action.dest: action.choices for action in fit._actions if action.choices}
    assert (choices["field"], choices["preset"]) == (tuple(DEFAULT_PRESETS), tuple(PRESET_KINDS))
