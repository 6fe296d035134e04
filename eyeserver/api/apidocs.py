"""``/api/v1/docs``: the OpenAPI document's interactive view, served with every asset it needs.

A treatment room's PC has no internet, and FastAPI's default page loads Swagger UI from a CDN,
so it came up blank there. The page here loads Swagger UI's script and style from the daemon
(``eyeserver/api/static/swagger-ui/``, the npm package ``swagger-ui-dist`` vendored unchanged:
:data:`SWAGGER_UI_VERSION`), under ``/api/v1/docs/assets/``; nothing it needs comes from
elsewhere. Like the document, it holds no data and needs no token when ``public_api_docs`` is on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["ASSETS", "SWAGGER_UI_VERSION", "mount"]

SWAGGER_UI_VERSION: Final = "5.35.0"
"""The vendored ``swagger-ui-dist`` (its README says how to update it)."""

ASSETS: Final = Path(__file__).parent / "static" / "swagger-ui"
"""Where the vendored files lie."""


def mount(app: FastAPI, prefix: str) -> None:
    """Serve the interactive view of ``app``'s OpenAPI document at ``{prefix}/docs``, its
    assets under ``{prefix}/docs/assets/`` (``app`` built with ``docs_url=None``)."""
    assets = f"{prefix}/docs/assets"
    app.mount(assets, StaticFiles(directory=ASSETS), name="swagger-ui")

    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=f"{prefix}/openapi.json", title=f"{app.title} API",
            swagger_js_url=f"{assets}/swagger-ui-bundle.js",
            swagger_css_url=f"{assets}/swagger-ui.css",
            swagger_favicon_url=f"{assets}/favicon-32x32.png")

    app.add_api_route(f"{prefix}/docs", docs, include_in_schema=False)
