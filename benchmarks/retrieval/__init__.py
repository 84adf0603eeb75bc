"""Retrievals against time on the single cloud, other scenes and the seed paper's field, and
what limits them."""
