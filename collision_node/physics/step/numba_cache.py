"""Where numba caches the compiled kernels: chosen before any kernel is decorated.

Every kernel module imports this module before ``numba.njit``, so each
dispatcher finds its cache in the folder chosen here. numba checks a cached
kernel against its own source file only, not against the compiled functions
it calls from other modules (``swept_kernels`` calls the law in
``contact_kernels``): a change there would load stale machine code. The
folder is therefore named by a digest of every physics source, and any
change compiles afresh.
"""

from __future__ import annotations

import hashlib
import os
from typing import Optional

import numba.core.config as _numba_config

# The physics package's folder: every source below it counts in the digest.
PHYSICS_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def sources_digest(here: Optional[str] = None) -> str:
    """Return a short digest of every physics module's source (under ``here``)."""
    here = here or PHYSICS_ROOT
    digest = hashlib.sha256()
    for folder, _dirs, files in sorted(os.walk(here)):
        for name in sorted(files):
            if name.endswith('.py'):
                with open(os.path.join(folder, name), 'rb') as source:
                    digest.update(name.encode() + b'\0' + source.read())
    return digest.hexdigest()[:16]


def cache_directory() -> str:
    """Return numba's cache directory for this version of the physics sources.

    Under ``NUMBA_CACHE_DIR`` if set, else the package's ``__pycache__``
    when writable, else the user's cache (``$XDG_CACHE_HOME`` or
    ``~/.cache``)/collision_node; each in a folder named by the digest.
    """
    here = PHYSICS_ROOT
    folder = f'numba-{sources_digest()}'
    if os.environ.get('NUMBA_CACHE_DIR'):
        return os.path.join(os.environ['NUMBA_CACHE_DIR'], 'collision_node', folder)
    pycache = os.path.join(here, '__pycache__')
    target = pycache if os.path.isdir(pycache) else here
    if os.access(target, os.W_OK):
        return os.path.join(pycache, folder)
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'collision_node', folder)


CACHE_DIR = cache_directory()
# Before the first compile: numba reads it when a dispatcher finds its cache.
_numba_config.CACHE_DIR = CACHE_DIR
