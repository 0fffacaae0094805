"""The one formatter of a one-line error (runfs.errors.one_line)."""

from runfs.errors import one_line


def test_one_line_joins_lines_names_an_empty_exception_and_cuts_to_the_limit():
    assert one_line("first\n  second\tthird") == "first second third"
    assert one_line(ValueError()) == "ValueError"
    assert one_line(OSError("disk\nfull")) == "disk full"
    assert one_line("x" * 50, 10) == "xxxxxxx..." and len(one_line("x" * 50, 10)) == 10
    assert one_line("short", 10) == "short"
