"""Rewrite the table of effects in docs/effects.md from the effect registry.

    python tools/effects_table.py          # update the file
    python tools/effects_table.py --check  # exit 1 if the file differs (tests do this too)
"""

from __future__ import annotations

import sys
from pathlib import Path

from tofhil.sim.effects import effects_table_markdown

DOC = Path(__file__).resolve().parents[1] / "docs" / "effects.md"
BEGIN = "<!-- effects-table:"
END = "<!-- end effects-table -->"


def with_table(text: str) -> str:
    """``text`` with the lines between the table's markers replaced by the generated table."""
    a = text.index(BEGIN)
    a = text.index("\n", a) + 1
    b = text.index(END)
    return text[:a] + effects_table_markdown() + text[b:]


def main() -> int:
    text = DOC.read_text()
    new = with_table(text)
    if "--check" in sys.argv[1:]:
        return 0 if new == text else 1
    DOC.write_text(new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
