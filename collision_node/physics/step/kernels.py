"""Every compiled kernel of the physics, prepared up front.

``prepare`` compiles the kernels (or loads them from the cache chosen in
``numba_cache``) and says how long that took, so a first start says why it
is slow and later starts pay nothing. A compile is single-threaded, so on a
machine with two or more cores it runs in two processes at once: a helper
process compiles one share of the modules into the cache while this one
compiles the other, then this one loads the helper's. This module imports
every kernel module; none of them imports it, so the kernels form no
import circle.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import Callable, Optional, Sequence

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

# The modules every other one calls: compiled first, so the shares below load them from the
# cache instead of compiling them twice (and never write the same cache entry at once).
SHARED = (primitives, step_kernels)
# Two shares of about equal compile time, each module after the modules it calls; the
# first is compiled by a helper process, the second by the process that prepares. The
# swept kernels take the most; the grid and contact kernels come next (`bench compile`).
SHARES = ((resting_kernels, event_kernels, swept_kernels, narrowphase_kernels, sleep_kernels,
           order_kernels),
          (wall_kernels, contact_kernels, separation_kernels, grid_kernels))

_PREPARED = False


def all_kernels() -> list:
    """Return every compiled kernel of the physics."""
    return [kernel for module in MODULES for kernel in module.kernels()]


def prepare(say: Optional[Callable[[str], None]] = None,
            processes: Optional[int] = None) -> float:
    """Compile the contact kernels, or load them from the cache; return the seconds taken.

    ``say`` (e.g. a logger's info) hears 'compiling ...' before a compile
    and how long it took after; loading from the cache is silent.
    ``processes`` caps the processes a compile runs in (None: 2 when this
    process may run on two cores or more; 1: all in this process). The
    compiled code is the same either way. Later calls do nothing and
    return 0.
    """
    global _PREPARED
    if _PREPARED:
        return 0.0
    compiling = not all(_cached(kernel) for kernel in all_kernels())
    if processes is None:
        processes = min(len(SHARES), _usable_cores())
    split = compiling and processes > 1
    if compiling and say is not None:
        say('compiling the contact kernels with numba (first start only; cached in '
            f'{CACHE_DIR}; in {2 if split else 1} process{"es" if split else ""})')
    start = time.perf_counter()
    if split:
        warm_modules(SHARED)
        helper = _start_helper(SHARES[0])
        try:
            warm_modules(SHARES[1])
            failed = helper.wait() != 0
        except BaseException:       # interrupted, or a kernel failed here: stop the helper
            helper.kill()
            helper.wait()
            raise
        if failed and say is not None:
            say('the helper process compiling '
                f'{", ".join(_names(SHARES[0]))} failed; compiling them here')
    warm_modules(MODULES)           # loads what the helper compiled (compiles what it did not)
    took = time.perf_counter() - start
    _PREPARED = True
    if compiling and say is not None:
        say(f'contact kernels compiled in {took:.1f} s')
    return took


def warm_modules(modules: Sequence) -> None:
    """Compile (or load) every kernel of ``modules``, in order."""
    for module in modules:
        module.warm_up()


def warm_named(names: Sequence[str]) -> None:
    """Compile the kernel modules named (their last dotted part): a helper process's work."""
    by_name = dict(zip(_names(MODULES), MODULES))
    warm_modules([by_name[name] for name in names])


def _names(modules: Sequence) -> list:
    return [module.__name__.rsplit('.', 1)[-1] for module in modules]


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # not on Linux
        return os.cpu_count() or 1


def _start_helper(modules: Sequence) -> subprocess.Popen:
    """Start a process compiling ``modules`` into the cache; it sees this process's path."""
    package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
        os.path.abspath(__file__)))))
    code = ('import sys\n'
            f'sys.path[:0] = {[package_root]!r}\n'
            'from collision_node.physics.step.kernels import warm_named\n'
            f'warm_named({_names(modules)!r})\n')
    return subprocess.Popen([sys.executable, '-c', code], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _cached(dispatcher) -> bool:
    """Say whether ``dispatcher`` has a cache of this source version (loading, not compiling)."""
    try:
        # An index of another source version loads as empty: that is a compile too.
        return bool(dispatcher._cache._cache_file._load_index())
    except (AttributeError, OSError, EOFError):    # another numba: assume a compile
        return False
