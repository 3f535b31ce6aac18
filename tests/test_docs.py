"""The documentation says what the code does: the scene kinds docs/formats.md lists are the
ones the scene loader accepts, every relative link resolves in a clone, and nothing points at
material a clone does not have."""

from __future__ import annotations

import re
import typing
from pathlib import Path

import pytest

from sim.render.scene import LENS_KINDS, SceneObject

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", ROOT / "benchmarks" / "README.md",
               *(ROOT / "docs").rglob("*.md"), *(ROOT / "benchmarks" / "results").glob("*.md")])
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
# the design notes outside the repository, tracker issues and development passes (the pattern
# is built from parts so that this file does not match it itself)
STALE = re.compile("|".join([r"\.\./" + "shared", "shared" + "/design",
                             r"(?:ARCHITECTURE|OPTICS|HARDWARE|BENCHMARKS|STYLE)\.md",
                             r"[Ii]ssues? \d+", r"\d+(?:st|nd|rd|th) pass"]))


def _table_kinds(section: str, heading: str) -> set[str]:
    """The backticked names in the first column of the table under ``heading``."""
    part = section.split(heading, 1)[1]
    rows = [ln for ln in part.split("\n\n", 2)[1].splitlines() if ln.startswith("| `")]
    return {re.match(r"\| `([^`]+)`", ln).group(1) for ln in rows}


def test_the_scene_kinds_in_the_formats_page_are_the_loaders():
    text = (ROOT / "docs" / "formats.md").read_text()
    scene = text.split("## Scene file (TOML)", 1)[1].split("\n## ", 1)[0]
    object_kinds = {typing.get_args(cls.model_fields["kind"].annotation)[0]
                    for cls in typing.get_args(typing.get_args(SceneObject)[0])}
    assert object_kinds == {"sphere", "ball_bar", "plane", "mesh", "board"}
    assert _table_kinds(scene, "**Objects**") == object_kinds
    assert _table_kinds(scene, "**Lenses**") == set(LENS_KINDS)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves_and_nothing_points_outside_the_clone(doc):
    text = doc.read_text()
    for target in LINK.findall(text):
        if "://" in target:
            continue
        assert (doc.parent / target).exists(), f"{doc.relative_to(ROOT)}: broken link {target}"
    stale = re.findall(STALE, text)
    assert not stale, f"{doc.relative_to(ROOT)} refers to {stale}"
