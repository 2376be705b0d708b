"""The documentation site builds with ``mkdocs build --strict`` (no broken link, no page
left out of the nav, no nav entry without its page), and its generated references list every
field of the protocol and device file schemas."""

from __future__ import annotations

import re
import subprocess
import sys
import types
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from dentibot.io.devices import DevicesConfig
from dentibot.protocol.schema import Protocol

ROOT = Path(__file__).resolve().parents[1]


def field_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every field of ``model`` and of the models inside it, as ``a.b[].c`` paths."""
    out = []
    for name, info in model.model_fields.items():
        path = prefix + name
        out.append(path)
        for suffix, inner in _models(info.annotation):
            out += field_paths(inner, f"{path}{suffix}.")
    return out


def _models(annotation) -> list[tuple[str, type[BaseModel]]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [("", annotation)]
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is list:
        return [("[]" + s, m) for s, m in _models(args[0])]
    if origin in (typing.Union, types.UnionType):
        return [x for a in args for x in _models(a)]
    return []


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_the_site_builds_strictly_with_every_page_of_the_nav(site):
    for page in ("index.html", "getting-started/index.html", "protocol-reference/index.html",
                 "hardware/index.html", "python-api/index.html", "recordings/index.html",
                 "architecture/index.html"):
        assert (site / page).is_file(), page
    # every marker of the generated sections was replaced
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        assert not re.search(r"<!-- (reference|signatures|include|value): ", text), page


@pytest.mark.parametrize("model, page", [(Protocol, "protocol-reference"),
                                         (DevicesConfig, "hardware")])
def test_the_reference_lists_every_field_of_the_schema(site, model, page):
    html = (site / page / "index.html").read_text(encoding="utf-8")
    paths = field_paths(model)
    assert len(paths) > 10
    missing = [p for p in paths if f"<code>{p}</code>" not in html]
    assert not missing, missing


def test_the_api_page_shows_every_public_function(site):
    import dentibot.api

    html = (site / "python-api" / "index.html").read_text(encoding="utf-8")
    for name in dentibot.api.__all__:
        assert f'id="{name.lower()}"' in html, name
