"""The table of every ``SVRNET_*`` setting in ``docs/configuration.md``, made from the settings
themselves (:class:`~service.core.settings.Settings`): name, default and meaning, so that a setting
added or changed shows in the docs (``tests/core/test_settings_docs.py`` checks it).

    .venv/bin/python -m tools.settings_docs          # rewrites the table between its markers

Example:
    >>> table().splitlines()[0]
    '| setting | default | meaning |'
    >>> [row for row in table().splitlines() if row.startswith("| `SVRNET_PORT`")]
    ['| `SVRNET_PORT` | 8000 | port the server listens on |']
"""

from __future__ import annotations

from pathlib import Path

from service.core.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "configuration.md"
BEGIN, END = "<!-- settings table: python -m tools.settings_docs -->", "<!-- end of settings table -->"


def _default(value: object) -> str:
    """A default as a user reads it: paths inside the repository relative to it, the home folder as ``~``."""
    if value is None:
        return "unset"
    if isinstance(value, Path):
        if value.is_relative_to(ROOT):
            return f"`{value.relative_to(ROOT).as_posix()}`"
        if value.is_relative_to(Path.home()):
            return f"`~/{value.relative_to(Path.home()).as_posix()}`"
    if value == "":
        return "empty"
    if isinstance(value, bool):
        return str(value).lower()
    return f"{value:g}" if isinstance(value, float) else str(value)


def table() -> str:
    """Every setting: ``SVRNET_<NAME>``, its default, its description."""
    rows = ["| setting | default | meaning |", "|---|---|---|"]
    for name, field in Settings.model_fields.items():
        text = (field.description or "").replace("|", "\\|").replace("<", "&lt;")
        rows.append(f"| `SVRNET_{name.upper()}` | {_default(field.default)} | {text} |")
    return "\n".join(rows)


def with_table(doc: str) -> str:
    """``doc`` with the text between its markers replaced by :func:`table`."""
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{table()}\n{END}{tail}"


def main() -> None:
    DOC.write_text(with_table(DOC.read_text()))


if __name__ == "__main__":
    main()
