"""The settings table of docs/settings.md against the ``Settings`` model (app/core/settings.py): one row per
field, named by its environment variable, with the field's default, and no row for a setting that is gone."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from app.core.settings import Settings

DOC = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
PREFIX = Settings.model_config["env_prefix"]
UNITS = {"KiB": 2**10, "MiB": 2**20, "GiB": 2**30}


def _table() -> dict[str, str]:
    """``{variable: default cell}`` of the table under the ``## Settings`` heading."""
    section = DOC.read_text().split("\n## Settings\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith(f"`{PREFIX}"):
            rows[cells[0].strip("`")] = cells[1]
    return rows


def _documented_default(cell: str) -> Any:
    """The value a default cell states: ``unset...`` is None, ``2 GiB`` bytes, ``64 000 000`` a number."""
    text = cell.replace("`", "").strip()
    if text.startswith("unset"):
        return None
    if match := re.fullmatch(r"([\d.]+) ([KMG]iB)", text):
        return float(match[1]) * UNITS[match[2]]
    if re.fullmatch(r"[\d .]+", text):
        return float(text.replace(" ", ""))
    if text.startswith("{"):
        return json.loads(text)
    return text


def _same(documented: Any, default: Any) -> bool:
    if isinstance(default, Path):
        return documented is not None and Path(documented) == default
    if isinstance(default, list):  # a comma-separated list: "unset" is the empty one
        return (documented or []) == default
    if isinstance(default, bool) or not isinstance(default, int | float):
        return documented == default
    return isinstance(documented, float) and documented == float(default)


def test_the_table_names_every_setting_and_nothing_else():
    documented = set(_table())
    expected = {f"{PREFIX}{name.upper()}" for name in Settings.model_fields}
    assert not expected - documented, f"settings missing from docs/settings.md: {sorted(expected - documented)}"
    assert not documented - expected, f"docs/settings.md documents unknown settings: {sorted(documented - expected)}"


@pytest.mark.parametrize("name", sorted(Settings.model_fields))
def test_the_table_states_each_default(name: str):
    cell = _table().get(f"{PREFIX}{name.upper()}")
    if cell is None:
        pytest.skip("missing row: reported by test_the_table_names_every_setting_and_nothing_else")
    default = Settings.model_fields[name].get_default(call_default_factory=True)
    assert _same(_documented_default(cell), default), f"{PREFIX}{name.upper()}: docs say {cell!r}, default {default!r}"
