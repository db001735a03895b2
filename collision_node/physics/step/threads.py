"""How many threads a world's compiled kernels run on: one setting for every entry point.

The runner's ``--threads N``, the node's read-only ``threads`` parameter
and the benchmarks' ``--threads`` all come here (0 or None: every thread
of numba's pool, which is the machine's cores unless ``NUMBA_NUM_THREADS``
says otherwise). A count of 1 runs every kernel's serial loop, the
single-thread kernels. Results never depend on the count: a parallel loop
writes each item's own result, whatever is gathered across items (kept
pairs, due impacts, energy) is gathered in item order afterwards, and a
contact solve large enough to share (``PARALLEL_MIN_ITEMS`` pairs) visits
its pairs colour by colour at every count, one included.
"""

from __future__ import annotations

from typing import Optional

import numba

from ..model.tunables import MAX_THREADS, PARALLEL_MIN_ITEMS
from ..model.validation import SceneError


# The count a world gets when it is given none (0: the whole pool); the
# benchmarks' --threads sets it for every world they build.
_default = 0


def set_default(count: Optional[int]) -> int:
    """Make ``count`` (0 or None: all cores) the count of worlds built without one; return it."""
    global _default
    resolved = resolve(count, '--threads')
    _default = resolved
    return resolved


def available() -> int:
    """Return the threads numba's pool holds in this process (its most per call)."""
    return int(numba.config.NUMBA_NUM_THREADS)


def resolve(count: Optional[int], where: str = 'threads') -> int:
    """Return the thread count ``count`` asks for (None: the default; 0: all of the pool's).

    Raises ``SceneError`` naming ``where`` for a count that is not an
    integer in 0 .. the pool's size.
    """
    if count is None:
        count = _default
    if isinstance(count, int) and not isinstance(count, bool) and count == 0:
        return available()
    if isinstance(count, bool) or not isinstance(count, int) or not 0 < count <= MAX_THREADS:
        raise SceneError(f'{where}: must be an integer in 0..{MAX_THREADS} (0: all cores), '
                         f'got {str(count)[:40]!r}')
    if count > available():
        raise SceneError(f'{where}: {count} threads asked for, but this process can run at '
                         f'most {available()} (the machine\'s cores; NUMBA_NUM_THREADS set '
                         'before the start raises it)')
    return count


def layer() -> str:
    """Return the threading layer numba's parallel loops run on ('omp', 'tbb', 'workqueue')."""
    try:
        return str(numba.threading_layer())
    except ValueError:          # no parallel loop has run yet in this process
        return 'none started'


def use(count: int) -> None:
    """Run the calling thread's parallel kernels on ``count`` threads (numba's is per thread)."""
    if numba.get_num_threads() != count:
        numba.set_num_threads(count)


def parallel(threads: int, items: int) -> bool:
    """Say whether a loop over ``items`` shares its work among ``threads`` threads."""
    return threads > 1 and items >= PARALLEL_MIN_ITEMS
