"""``/api/image/{path}``: stored pictures, confined to the artifacts folder.

A file is served only when all hold:

- ``path`` is relative, without ``..``, empty or hidden (``.``) parts;
- it is an artifact: some stored layer result names it (table ``artifacts``);
- its suffix is a picture's (``.png``, ``.jpg``, ``.jpeg``, ``.webp``);
- the fully resolved file (symbolic links followed) lies inside the resolved
  artifacts folder, and is none of the database, its WAL/SHM/journal or the
  token file (even if someone points the artifacts folder at their folder).
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse

from layerwatch.web.context import Ctx, Dashboard

__all__ = ["router", "IMAGE_SUFFIXES", "servable"]

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".webp"})
router = APIRouter(prefix="/api")


def servable(ctx: Dashboard, path: str) -> Path | None:
    """The file ``/api/image/{path}`` may serve, or ``None``."""
    root = ctx.image_root
    rel = PurePosixPath(path)
    if root is None or not path or "\\" in path or "\x00" in path or rel.is_absolute():
        return None
    if any(part in ("", "..") or part.startswith(".") for part in rel.parts):
        return None
    if rel.suffix.lower() not in IMAGE_SUFFIXES or not ctx.history.is_artifact(path):
        return None
    try:
        target = (root / rel).resolve(strict=True)
    except (OSError, RuntimeError, ValueError):
        return None
    if not target.is_relative_to(root) or target in ctx.private or not target.is_file():
        return None
    return target


@router.get("/image/{path:path}", summary="A stored picture (an artifact of a layer) under the artifacts folder")
def image(ctx: Ctx, path: str) -> FileResponse:
    target = servable(ctx, path)
    if target is None:
        raise HTTPException(404, "not found")
    return FileResponse(target, headers={"Cache-Control": "private, max-age=3600"})
