"""The docs' relative links lead somewhere: every `[text](file#anchor)` in README.md and docs/*.md names a
file that exists and, for a markdown file, a heading in it (GitHub's anchors). Seven anchors still named
the commands' old modules (`#compensating-a-path-python--m-pipelinepath`) after they moved."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCED = re.compile(r"^```.*?^```", re.S | re.M)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped but hyphens, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set:
    seen, out = {}, set()
    for heading in re.findall(r"^#{1,6}\s+(.+)$", FENCED.sub("", page.read_text()), re.M):
        s = slug(heading)
        out.add(s if s not in seen else f"{s}-{seen[s]}")      # a repeated heading: -1, -2, ...
        seen[s] = seen.get(s, 0) + 1
    return out


def test_slug_is_github_s():
    assert slug("At a tool's centre point: `--tcp NAME`") == "at-a-tools-centre-point---tcp-name"
    assert slug("Compensating a path: `python -m pipeline.commands.path`") == \
        "compensating-a-path-python--m-pipelinecommandspath"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_names_a_file_and_heading_that_exist(page):
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", FENCED.sub("", page.read_text())):
        if re.match(r"^[a-z]+:", target):                          # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        f = (page.parent / path) if path else page
        if not f.exists():
            bad.append(f"{target}: no such file")
        elif anchor and f.suffix == ".md" and anchor not in anchors(f):
            bad.append(f"{target}: no such heading in {f.name}")
    assert not bad, bad
