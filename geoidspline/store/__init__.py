"""The tile store on disk (thesis §4.3, §6.1: local tiles put together).

- :mod:`.format`: file names, the manifest schema, tile files (format 2 and 1);
- :mod:`.codec`: the coded tiles of formats 2 and 3 (key runs, quantised predicted values, Zstandard);
- :mod:`.writer`: the writer lock and the atomic commit;
- :mod:`.reader`: :class:`~.reader.TileStore`, opened read-only, tiles read lazily;
- :mod:`.update`: regional updates, rewriting only the tiles they touch;
- :mod:`.upgrade`: a format-1 store rewritten in format 2 (``geoid-info --upgrade``).
"""

from .reader import TileStore, verify_store

__all__ = ["TileStore", "verify_store"]
