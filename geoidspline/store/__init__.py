"""The tile store on disk (thesis §4.3, §6.1: local tiles put together).

- :mod:`.format`: file names, the manifest schema, tile files;
- :mod:`.writer`: the writer lock and the atomic commit;
- :mod:`.reader`: :class:`~.reader.TileStore`, opened read-only, tiles read lazily;
- :mod:`.update`: regional updates, rewriting only the tiles they touch.
"""

from .reader import TileStore, verify_store

__all__ = ["TileStore", "verify_store"]
