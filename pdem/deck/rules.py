"""Helpers for deck-time checks of plugin parameters (the ``rules(data, context)`` classmethods of
source and boundary ``Params``): public names for what pdem's own deck schema uses.

* :data:`REGION_MODELS`, :data:`SIZE_MODELS` — the ``region`` and ``sizes`` table models by ``type``;
* :func:`try_build` — build one of those from raw deck data, or None if it does not validate;
* :func:`fit_problem` — a problem when the largest radius does not fit in a region;
* :func:`given` — whether a key is present and not None; :func:`is_number` — a real number (not bool);
* :func:`context_of` — the validation context (``base_dir``, …) of a pydantic validator.
"""

from __future__ import annotations

from .schema import (
    _REGION_MODELS as REGION_MODELS,
)
from .schema import (
    _SIZE_MODELS as SIZE_MODELS,
)
from .schema import (
    _ctx as context_of,
)
from .schema import (
    _fit_problem as fit_problem,
)
from .schema import (
    _given as given,
)
from .schema import (
    _is_num as is_number,
)
from .schema import (
    _try_build as try_build,
)

__all__ = ["REGION_MODELS", "SIZE_MODELS", "try_build", "fit_problem", "given", "is_number", "context_of"]
