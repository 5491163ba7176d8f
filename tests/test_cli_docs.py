"""docs/cli.md is generated from the parser (scripts/make_cli_docs.py) and must stay in sync."""

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("make_cli_docs", REPO / "scripts" / "make_cli_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_cli_md_matches_the_parser():
    generator = _generator()
    expected = generator.render_cli_docs()
    current = (REPO / "docs" / "cli.md").read_text()
    assert current == expected, "docs/cli.md is out of date: run python scripts/make_cli_docs.py"


def test_docs_cli_md_has_every_command_and_old_spelling():
    generator = _generator()
    text = (REPO / "docs" / "cli.md").read_text()
    parser = generator.build_parser()
    for name in generator.subcommands(parser):
        assert f"\n## {name}\n" in text and f"usage: gscodec-shac {name}" in text
    for command, old, new in generator.aliases(parser):
        assert f"| `{command}` | `{old}` | `{new}` |" in text
    assert ("render", "--images-dir", "--images") in generator.aliases(parser)
