"""Synthetic cloud fields for tests and tutorials (the LES readers are in cloudct.les)."""
