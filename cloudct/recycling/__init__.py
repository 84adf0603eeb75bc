"""Path recycling (seed paper Sec. 5): not implemented yet (issue 6)."""
