"""The front door and the documentation site.

- The site (mkdocs.yml, docs/) builds with `mkdocs build --strict`: a broken link, a broken anchor,
  a page missing from the nav or a nav entry without its page fails, and the built pages load no
  font or script from the network (the site builds and reads offline).
- The strict build really fails on a broken link and on a missing page (checked on a copy).
- README.md is at most 250 lines, every relative link and image in it exists, and it keeps the two
  quickstart commands.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_LINES = 250
# [text](target) and ![alt](target), the target up to the first space or closing parenthesis
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def mkdocs_build(project: Path, site: Path) -> subprocess.CompletedProcess:
    env = os.environ | {"NO_MKDOCS_2_WARNING": "1"}  # Material's end-of-life notice, not a build problem
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(project / "mkdocs.yml")]
        + ["--site-dir", str(site)],
        cwd=project,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def copy_project(dest: Path) -> Path:
    """mkdocs.yml and docs/ (symlinks resolved, so the copy needs nothing outside it)."""
    dest.mkdir()
    shutil.copy2(ROOT / "mkdocs.yml", dest / "mkdocs.yml")
    shutil.copytree(ROOT / "docs", dest / "docs", symlinks=False)
    return dest


def test_the_site_builds_in_strict_mode_and_offline(tmp_path):
    out = mkdocs_build(ROOT, tmp_path / "site")
    assert out.returncode == 0, out.stdout + out.stderr
    pages = list((tmp_path / "site").rglob("*.html"))
    assert len(pages) > 10
    for page in pages:
        html = page.read_text(encoding="utf-8")
        assert "fonts.googleapis.com" not in html and "fonts.gstatic.com" not in html, page
    assert (tmp_path / "site" / "lab-notebook" / "index.html").is_file()


def test_a_broken_link_fails_the_build(tmp_path):
    project = copy_project(tmp_path / "project")
    page = project / "docs" / "results.md"
    page.write_text(page.read_text(encoding="utf-8") + "\nSee [a page that is not there](no-such-page.md).\n")
    out = mkdocs_build(project, tmp_path / "site")
    assert out.returncode != 0
    assert "no-such-page.md" in out.stdout + out.stderr


def test_a_broken_anchor_fails_the_build(tmp_path):
    project = copy_project(tmp_path / "project")
    page = project / "docs" / "results.md"
    page.write_text(page.read_text(encoding="utf-8") + "\nSee [nothing](performance.md#no-such-section).\n")
    out = mkdocs_build(project, tmp_path / "site")
    assert out.returncode != 0
    assert "no-such-section" in out.stdout + out.stderr


def test_a_missing_page_fails_the_build(tmp_path):
    project = copy_project(tmp_path / "project")
    (project / "docs" / "scaling.md").unlink()
    out = mkdocs_build(project, tmp_path / "site")
    assert out.returncode != 0
    assert "scaling.md" in out.stdout + out.stderr


def readme_targets() -> list[str]:
    text = README.read_text(encoding="utf-8")
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # code blocks hold commands, not links
    return LINK.findall(text)


def test_readme_is_a_front_door_of_at_most_250_lines():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; the rest belongs in docs/"


def test_every_relative_link_and_image_in_the_readme_exists():
    targets = readme_targets()
    assert any(t.endswith(".png") for t in targets), "the README shows a picture on its first screen"
    missing = []
    for target in targets:
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL, or an anchor of the README itself
        path = target.split("#", 1)[0]
        if not (ROOT / path).exists():
            missing.append(target)
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_the_readme_has_a_picture_on_its_first_screen():
    first_screen = "\n".join(README.read_text(encoding="utf-8").splitlines()[:40])
    assert re.search(r"!\[[^\]]*\]\([^)]+\.png\)", first_screen)


@pytest.mark.parametrize(
    "command",
    [
        "python3.11 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e '.[pipeline]' && dvc repro",
        "bash .ci/run",
    ],
)
def test_the_readme_keeps_the_two_quickstart_commands(command):
    assert command in README.read_text(encoding="utf-8")
