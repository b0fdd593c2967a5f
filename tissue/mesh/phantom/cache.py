"""The on-disk mesh cache: where generated meshes are stored and how they are read back.

Each entry is one ``.npz`` file (:func:`tissue.mesh.io.save_mesh_npz`), written atomically,
named by its caller (:func:`~tissue.mesh.phantom.breast_phantom` keys it by
:data:`~tissue.mesh.phantom.GENERATOR_VERSION`, level and spec hash). A damaged entry is
regenerated; an unwritable directory costs the cache, not the mesh.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from pathlib import Path

from tissue.errors import MeshError
from tissue.mesh import TetMesh

#: Environment variable that overrides the cache directory.
CACHE_ENV_VAR = "PROBEGYM_CACHE_DIR"


def mesh_cache_dir(cache_dir: str | Path | None = None) -> Path:
    """The directory generated meshes are cached in.

    ``cache_dir`` if given, else ``$PROBEGYM_CACHE_DIR`` if set, else the platform's user
    cache directory for ``probegym`` (``~/.cache/probegym`` on Linux).
    """
    if cache_dir is not None:
        return Path(cache_dir)
    from_env = os.environ.get(CACHE_ENV_VAR)
    if from_env:
        return Path(from_env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("probegym"))


def cached_mesh(path: Path, generate: Callable[[], TetMesh]) -> TetMesh:
    """Load ``path`` if present, else generate, store atomically and return the stored copy.

    Returning what was read back makes a fresh mesh and a cache hit identical. A cache
    directory that cannot be written costs the cache, not the mesh (a warning says so).
    """
    from tissue.mesh.io import load_mesh_npz, save_mesh_npz

    if path.is_file():
        try:
            return load_mesh_npz(path)
        except MeshError:
            pass  # stale or damaged entry: regenerate and overwrite it
    mesh = generate()
    try:
        save_mesh_npz(mesh, path)
    except OSError as error:
        warnings.warn(f"cannot cache mesh in {str(path)!r}: {error}", stacklevel=3)
        return mesh
    return load_mesh_npz(path)
