"""docs/guides/imports-notes.md: every config snippet is a valid flylib config fragment
(merged over the default config, validated as the workflow validates it)."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest
import yaml

from flylib.config import Config, validate_config
from flylib.config.layers import merge_tables
from flylib.interop.importer import import_spec

PAGE = Path(__file__).resolve().parents[2] / "docs" / "guides" / "imports-notes.md"
SNIPPETS = re.findall(r"```yaml\n(.*?)```", PAGE.read_text(), flags=re.S)


def test_the_page_has_its_snippets():
    assert len(SNIPPETS) == 3


@pytest.mark.parametrize("snippet", SNIPPETS)
def test_each_snippet_is_a_valid_config_fragment(snippet):
    fragment = yaml.safe_load(snippet)
    data = merge_tables(copy.deepcopy(Config.default().data), fragment)
    assert validate_config(data) == []
    spec = (fragment.get("pose2d") or {}).get("import")
    if spec is not None:
        assert import_spec(spec) == spec
