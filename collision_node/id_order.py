"""A world's particles in id order, for outputs: each array sorted when first read.

Outputs (the node's messages, the runner's JSON, recordings) give particles
in id order. A large world keeps its rows in spatial order instead
(``physics/stages/ordering``), so an output sorts them; a message reads only
some of the arrays (poses read the positions alone), and a sorted copy of
1,000,000 rows costs tens of milliseconds each, so each array is sorted
when an output first reads it and kept for the others of the same tick.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .physics.model.state import id_order, ids_ascending, ParticleState


class InIdOrder:
    """A read-only view of a state with its rows in id order, each array sorted when read.

    Reads the same attributes as a ``ParticleState`` (``ids``, ``position``,
    ``velocity``, ...); a state already in id order is read as it is.
    """

    def __init__(self, state: ParticleState) -> None:
        """Keep the state and, if its rows are not in id order, the order that sorts them."""
        self._state = state
        self._order = None if ids_ascending(state.ids) else id_order(state.ids)
        self._sorted: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        """Return the number of particles."""
        return len(self._state)

    def __getattr__(self, name: str) -> Any:
        """Return the state's attribute ``name``, its rows in id order."""
        value = getattr(self._state, name)
        if self._order is None or not isinstance(value, np.ndarray) \
                or value.shape[:1] != self._order.shape:
            return value
        if name not in self._sorted:
            self._sorted[name] = value[self._order]
        return self._sorted[name]
