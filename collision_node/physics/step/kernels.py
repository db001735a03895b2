"""Every compiled kernel of the physics, prepared up front.

``prepare`` compiles the kernels (or loads them from the cache chosen in
``numba_cache``) and says how long that took, so a first start says why it
is slow and later starts pay nothing. This module imports every kernel
module; none of them imports it, so the kernels form no import circle.
"""

from __future__ import annotations

import time
from typing import Callable, Optional

from ..law import primitives
from ..stages.solve import contact_kernels, wall_kernels
from ..stages.events import event_kernels, resting_kernels
from ..stages.detection import grid_kernels, narrowphase_kernels
from ..stages.correction import separation_kernels
from ..stages.sleeping import sleep_kernels
from ..stages.ordering import order_kernels
from . import step_kernels
from ..stages.swept import swept_kernels
from .numba_cache import CACHE_DIR

# Each module gives warm_up() (call every kernel once on a tiny problem) and kernels().
MODULES = (primitives, contact_kernels, narrowphase_kernels, separation_kernels, swept_kernels,
           sleep_kernels, event_kernels, resting_kernels, grid_kernels, wall_kernels, step_kernels,
           order_kernels)

_PREPARED = False


def all_kernels() -> list:
    """Return every compiled kernel of the physics."""
    return [kernel for module in MODULES for kernel in module.kernels()]


def prepare(say: Optional[Callable[[str], None]] = None) -> float:
    """Compile the contact kernels, or load them from the cache; return the seconds taken.

    ``say`` (e.g. a logger's info) hears 'compiling ...' before a compile
    and how long it took after; loading from the cache is silent. Later
    calls do nothing and return 0.
    """
    global _PREPARED
    if _PREPARED:
        return 0.0
    compiling = not all(_cached(kernel) for kernel in all_kernels())
    if compiling and say is not None:
        say('compiling the contact kernels with numba (first start only; cached in '
            f'{CACHE_DIR})')
    start = time.perf_counter()
    for module in MODULES:
        module.warm_up()
    took = time.perf_counter() - start
    _PREPARED = True
    if compiling and say is not None:
        say(f'contact kernels compiled in {took:.1f} s')
    return took


def _cached(dispatcher) -> bool:
    """Say whether ``dispatcher`` has a cache of this source version (loading, not compiling)."""
    try:
        # An index of another source version loads as empty: that is a compile too.
        return bool(dispatcher._cache._cache_file._load_index())
    except (AttributeError, OSError, EOFError):    # another numba: assume a compile
        return False
