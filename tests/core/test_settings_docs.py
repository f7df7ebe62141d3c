"""docs/configuration.md lists every setting with its default, made from the settings themselves
(``tools/settings_docs.py``): a setting added or changed without it fails here."""

from __future__ import annotations

from service.core.settings import Settings
from tools.settings_docs import DOC, table, with_table


def test_the_settings_table_is_what_the_settings_say() -> None:
    doc = DOC.read_text()
    assert with_table(doc) == doc, "docs/configuration.md is out of date: make config-docs"
    for name in Settings.model_fields:
        assert f"| `SVRNET_{name.upper()}` |" in doc
    assert "| `SVRNET_RETENTION_HOURS` | 72 |" in table() and "| `SVRNET_DATA_DIR` | `~/.svrnet` |" in table()
