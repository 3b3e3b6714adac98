"""``python -m pdem``: the ``pdem`` command (for launchers that have the interpreter, not the script)."""

from .cli import main

raise SystemExit(main())
