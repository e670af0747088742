"""A section's table goes between its markers in a doc, and nowhere else."""

from __future__ import annotations

import pytest

from harness.bench.doc_block import replace_block

BEGIN, END = "<!-- t:begin -->", "<!-- t:end -->"


def test_the_block_is_replaced_and_the_page_around_it_kept(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(f"# Title\n\nbefore\n{BEGIN}\nold | table\n{END}\nafter, with {END} again\n")
    replace_block(page, BEGIN, END, ["| new |", "", "second"])
    assert page.read_text() == (
        f"# Title\n\nbefore\n{BEGIN}\n| new |\n\nsecond\n{END}\nafter, with {END} again\n"
    )
    replace_block(page, BEGIN, END, ["| new |", "", "second"])  # a second run changes nothing
    assert page.read_text().count("| new |") == 1


@pytest.mark.parametrize("text", ["no markers\n", f"{END}\nend before begin\n{BEGIN}\n"])
def test_a_page_without_its_markers_is_left_alone_and_named(tmp_path, text):
    page = tmp_path / "page.md"
    page.write_text(text)
    with pytest.raises(ValueError, match=r"page\.md has no"):
        replace_block(page, BEGIN, END, ["x"])
    assert page.read_text() == text
