"""The README and docs/: short README, the two commands, working links, real commands."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = sorted((REPO / "docs").glob("*.md"))
LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_readme_is_short_and_starts_with_the_two_commands():
    text = README.read_text()
    assert len(text.split()) < 1000  # `wc -w README.md`
    first_block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    assert [line.split("#")[0].strip() for line in first_block.splitlines()] == ["make demo", "make test"]
    assert "make test" in (REPO / ".ci" / "run").read_text()


def test_every_docs_page_is_linked_from_the_readme():
    links = set(LINK.findall(README.read_text()))
    assert {f"docs/{p.name}" for p in DOCS} <= links


def test_relative_links_resolve():
    for page in [README, *DOCS]:
        for target in LINK.findall(page.read_text()):
            if target.startswith(("http://", "https://")):
                continue
            path = target.split("#", 1)[0]
            assert (page.parent / path).exists(), f"{page.name}: broken link {target}"


def test_documented_commands_exist():
    from mogaf.bench.__main__ import available

    benches = set(available())
    ablations = yaml.safe_load((REPO / "config" / "ablations.yaml").read_text())
    sweeps = {f"sweep_{name}" for name in ablations["sweeps"]}
    makefile = (REPO / "Makefile").read_text()
    for page in [README, *DOCS]:
        text = page.read_text()
        for name in re.findall(r"python -m mogaf\.bench (\w+)", text):
            assert name in benches, f"{page.name}: no benchmark {name}"
        for name in re.findall(r"\bsweep_(\w+)", text):
            assert f"sweep_{name}" in sweeps, f"{page.name}: no target sweep_{name}"
        for target in re.findall(r"`make (\w+)", text):
            assert re.search(rf"^{target}:", makefile, re.M), f"{page.name}: no make target {target}"
