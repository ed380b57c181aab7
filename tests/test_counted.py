"""counted: a count and its noun, singular for 1 alone."""

from artnvg_core.counted import counted


def test_a_count_of_one_takes_the_singular_and_others_the_plural():
    assert counted(1, "view") == "1 view"  # the command line once printed "rendering 1 views"
    assert [counted(n, "view") for n in (0, 2, 24)] == ["0 views", "2 views", "24 views"]
    assert counted(100000, "Gaussian") == "100,000 Gaussians"
    assert (counted(1, "property", "properties"), counted(3, "property", "properties")) == ("1 property", "3 properties")
