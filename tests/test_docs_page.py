"""The API docs in headless Chromium with no way off the machine: everything they need is ours."""

from __future__ import annotations

from urllib.parse import urlparse

import pytest

pytestmark = pytest.mark.browser


def test_the_api_docs_render_offline(serve_app, browser):
    base_url, _ = serve_app()
    page = browser.new_page()
    outside = []

    def only_this_server(route):
        if urlparse(route.request.url).netloc == urlparse(base_url).netloc:
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", only_this_server)
    page.goto(base_url + "/docs")
    page.wait_for_selector(".opblock", timeout=15_000)  # Swagger UI drew the operations
    assert outside == [], "the docs reached off the machine"
    assert "/api/messages" in page.content()
