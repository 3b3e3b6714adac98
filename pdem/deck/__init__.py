"""The deck layer: TOML decks, validated in full before anything runs.

``load_deck(path, overrides)`` reads a TOML deck, applies ``--set key.path=value`` overrides, validates
everything (schema, cross-references, plugin parameters) and returns a :class:`ResolvedDeck`, or raises
one :class:`~pdem.errors.DeckError` listing every problem with its key path. The deck format is
documented key by key in ``docs/deck.md``; :func:`deck_json_schema` gives a JSON Schema for editors.
"""

from .load import ResolvedDeck, deck_json_schema, installed_writers, load_deck, validate_deck
from .overrides import OverrideError, apply_overrides, parse_override
from .schema import Deck

__all__ = [
    "Deck",
    "ResolvedDeck",
    "load_deck",
    "validate_deck",
    "deck_json_schema",
    "installed_writers",
    "parse_override",
    "apply_overrides",
    "OverrideError",
]
