"""``/ui``: the web dashboard (issue #18 item 5), one static page with vanilla JS (``service/static``).

The page itself holds no data and needs no key; everything it shows it fetches from ``/v1`` with the API key
the user enters (kept in the browser, sent as Bearer), so the job routes' key scoping applies unchanged.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse, RedirectResponse

PAGE = Path(__file__).resolve().parent.parent / "static" / "dashboard.html"

router = APIRouter(include_in_schema=False)


@cache
def _page() -> str:
    return PAGE.read_text(encoding="utf-8")


@router.get("/ui", response_class=HTMLResponse)
def dashboard() -> HTMLResponse:
    # no-store: a new deployment's page is picked up at once; the page is a few kilobytes.
    return HTMLResponse(_page(), headers={"Cache-Control": "no-store"})


@router.get("/", response_class=RedirectResponse)
def root() -> RedirectResponse:
    return RedirectResponse("/ui")
