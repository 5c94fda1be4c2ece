"""layerwatch.storage: the print history (SQLite)."""

from layerwatch.storage.history import History

__all__ = ["History"]
