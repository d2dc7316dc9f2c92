"""Studies: published results a scenario is compared against (tables, figure windows,
reference lines)."""
