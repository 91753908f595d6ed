"""The live view's page text is package data: installed with the package, inlined, hashed."""

from __future__ import annotations

import base64
import hashlib
import re
import tomllib
from pathlib import Path

from temoto.web import _page
from temoto.web.server import _page_bytes

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "temoto" / "web" / "static"


def test_every_page_file_is_package_data() -> None:
    """A wheel (``pip install .``, not editable) carries every file the page is made of."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = config["package-data"]["temoto"]
    installed = {p for pattern in patterns for p in (ROOT / "temoto").glob(pattern)}
    files = sorted(STATIC.iterdir())
    assert {f.name for f in files} >= {"page.css", "page.js", "body.html"}
    assert [f.name for f in files if f not in installed] == []
    excluded = config.get("exclude-package-data", {}).get("*", [])
    assert not [f.name for f in files if any(f.match(x) for x in excluded)]


def test_the_page_inlines_its_files_and_the_policy_allows_exactly_them() -> None:
    html, policy = _page_bytes("replay")
    text = html.decode()
    assert (STATIC / "page.js").read_text(encoding="utf-8") in text
    assert (STATIC / "page.css").read_text(encoding="utf-8") in text
    assert (STATIC / "body.html").read_text(encoding="utf-8") in text
    (script,) = re.findall(r"<script>(.*?)</script>", text, re.S)
    (style,) = re.findall(r"<style>(.*?)</style>", text, re.S)
    assert script == _page.js() == _page.JS
    assert style == _page.css() == _page.CSS

    def digest(body: str) -> str:
        return base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()

    assert f"script-src 'sha256-{digest(script)}'" in policy
    assert f"style-src 'sha256-{digest(style)}'" in policy
    assert '.node[data-state="RUNNING"] rect' in style  # the generated per-state rules
