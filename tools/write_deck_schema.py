#!/usr/bin/env python
"""Write docs/deck.schema.json, the JSON Schema of pdem decks, for editors.

    python tools/write_deck_schema.py [--output docs/deck.schema.json] [--all-plugins] [--check]

By default the schema documents pdem's own contact laws, particle sources and boundary plugins
only, so that the committed file does not depend on what else is installed; ``--all-plugins``
includes every installed plugin (``pdem schema`` prints that version). ``--check`` writes nothing
and exits 1 if the file is out of date. Point an editor at the file, e.g. with Even Better TOML
(Taplo), on the first line of a deck::

    #:schema ../docs/deck.schema.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pdem.deck import deck_json_schema

DEFAULT = Path(__file__).resolve().parent.parent / "docs" / "deck.schema.json"


def render(all_plugins: bool = False) -> str:
    """The schema as indented JSON text (stable key order, trailing newline)."""
    return json.dumps(deck_json_schema(builtin_only=not all_plugins), indent=2, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", type=Path, default=DEFAULT, help=f"default {DEFAULT}")
    p.add_argument("--all-plugins", action="store_true", help="document every installed plugin")
    p.add_argument("--check", action="store_true", help="exit 1 if the file is out of date")
    args = p.parse_args(argv)
    text = render(args.all_plugins)
    if args.check:
        current = args.output.read_text(encoding="utf-8") if args.output.exists() else ""
        if current != text:
            print(f"{args.output} is out of date; run python tools/write_deck_schema.py", file=sys.stderr)
            return 1
        print(f"{args.output} is up to date")
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text, encoding="utf-8")
    print(f"wrote {args.output} ({len(text)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
