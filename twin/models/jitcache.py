"""numba's on-disk cache kept in step with the modules a kernel's machine code was compiled from.

numba checks a cached function against its own source file only. A kernel that calls the compiled
functions of another module, or reads its constants (the tracker's filter reads the rig model's
kernel layout ``I_*`` and inlines its right-hand side), keeps its old machine code after that other
module changed: wrong numbers, silently (seen when the MSP25 kernel layout grew while ``ukf.py``
stayed the same). :func:`keep_fresh`, called by such a module before its first ``cache=True``
decorator runs, removes the module's cached code when any module it depends on changed since the
code was cached. A fresh install compiles afresh anyway; this matters to whoever edits the models.
With ``NUMBA_CACHE_DIR`` set the cache lives elsewhere and is not checked here.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def keep_fresh(module_file: str, *dependencies: str) -> bool:
    """Drop ``module_file``'s numba cache when the source of any of ``dependencies`` (module files) differs from
    what it was when the cache was written; returns whether anything was dropped. Never raises: a cache that
    cannot be read or written is numba's to handle."""
    try:
        digest = hashlib.sha256()
        for dep in sorted(dependencies):
            digest.update(Path(dep).read_bytes())
        stamp_text = digest.hexdigest()
        here = Path(module_file)
        cache = here.parent / "__pycache__"
        stamp = cache / f"{here.stem}.deps"
        try:
            if stamp.read_text() == stamp_text:
                return False
        except OSError:
            pass
        dropped = False
        for f in list(cache.glob(f"{here.stem}.*.nbi")) + list(cache.glob(f"{here.stem}.*.nbc")):
            f.unlink(missing_ok=True)
            dropped = True
        cache.mkdir(exist_ok=True)
        stamp.write_text(stamp_text)
        return dropped
    except OSError:
        return False
