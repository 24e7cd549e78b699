"""The fleet's coordinator: which member heads for which view (issue 17)."""
