"""carotid: from a CT angiogram of the neck to a verified blood-flow simulation of the carotid bifurcation."""

import os
import tempfile
from pathlib import Path

__version__ = "0.1.0"


def numba_cache_dir(package: Path, environ) -> str | None:
    """Where numba should cache the compiled kernels when it cannot next to their sources, or None.

    The kernels are compiled with ``cache=True``; numba writes the cache beside the sources, else under the
    user's home, and where neither is writable (a read-only install in a container without a home) it stops
    at import with a traceback.  A folder of the system's temporary one is then used, unless
    ``NUMBA_CACHE_DIR`` is set.

    Parameters
    ----------
    package : Path
        The package's folder.
    environ : mapping
        The environment.
    """
    if "NUMBA_CACHE_DIR" in environ or os.access(package, os.W_OK):
        return None
    return os.path.join(tempfile.gettempdir(), f"carotid-numba-{os.getuid() if hasattr(os, 'getuid') else 0}")


_cache = numba_cache_dir(Path(__file__).parent, os.environ)
if _cache is not None:
    os.environ["NUMBA_CACHE_DIR"] = _cache
