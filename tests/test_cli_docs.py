"""docs/cli.md is generated from the parser (scripts/make_cli_docs.py) and must stay in sync."""

from tests.conftest import REPO_ROOT, load_script


def test_docs_cli_md_matches_the_parser():
    generator = load_script("make_cli_docs")
    expected = generator.render_cli_docs()
    current = (REPO_ROOT / "docs" / "cli.md").read_text()
    assert current == expected, "docs/cli.md is out of date: run python scripts/make_cli_docs.py"


def test_docs_cli_md_has_every_command_and_old_spelling():
    generator = load_script("make_cli_docs")
    text = (REPO_ROOT / "docs" / "cli.md").read_text()
    parser = generator.build_parser()
    for name in generator.subcommands(parser):
        assert f"\n## {name}\n" in text and f"usage: gscodec-shac {name}" in text
    for command, old, new in generator.aliases(parser):
        assert f"| `{command}` | `{old}` | `{new}` |" in text
    assert ("render", "--images-dir", "--images") in generator.aliases(parser)
